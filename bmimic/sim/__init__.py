"""Batched MuJoCo-Warp simulation layer."""

from bmimic.sim.config import SimConfig
from bmimic.sim.simulator import Simulator, apply_sim_options

__all__ = ["SimConfig", "Simulator", "apply_sim_options"]
