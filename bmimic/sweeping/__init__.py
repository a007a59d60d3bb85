"""Sweeps (Hydra multiruns) around the training jobs: their expansion for the dry run (`jobs`), GPU
slots for parallel jobs on one machine (`gpu_slots`) and how the jobs ended (`outcomes`). Torch-free:
Hydra's launcher and callbacks import it."""
