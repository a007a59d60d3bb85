#!/bin/bash
# One training run across the GPUs of several SLURM nodes: srun starts one torchrun per node,
# each torchrun one rank per GPU, and all ranks meet at the job's first node (c10d rendezvous).
#
#   sbatch --nodes 2 sweeps/slurm_multinode.sh num_envs=4096 run_name=walk motion=lafan_walk1
#
# Submit from the folder that should hold outputs/, with bmimic's Python environment active (sbatch
# passes the environment on). Arguments after the script are overrides of `python -m bmimic.train`.
# num_envs is per GPU. The run folder is outputs/runs/<run_name>/slurm-<job id>, the same for every
# rank; rank 0 writes the run. To continue one, pass resume=<its run folder> on a file system that
# every node sees (each rank loads the checkpoint).
# GPUS_PER_NODE (default: SLURM's count, else 8) and RDZV_PORT (default: 29500 + job id mod 1000)
# can be set in the environment.
#SBATCH --job-name=bmimic
#SBATCH --nodes=2
#SBATCH --ntasks-per-node=1
#SBATCH --gpus-per-node=8
#SBATCH --cpus-per-task=32
#SBATCH --time=12:00:00
set -euo pipefail

gpus_per_node=${GPUS_PER_NODE:-${SLURM_GPUS_ON_NODE:-8}}
# sed reads every line: `head -n 1` would exit early and, under pipefail, a SIGPIPE to scontrol
# would end the script (exit 141).
head_node=$(scontrol show hostnames "$SLURM_JOB_NODELIST" | sed -n 1p)
port=${RDZV_PORT:-$((29500 + SLURM_JOB_ID % 1000))}

# One task per node; --kill-on-bad-exit ends the other nodes when one fails, instead of leaving
# them waiting in a collective until the process group's timeout.
srun --ntasks-per-node=1 --kill-on-bad-exit=1 \
    torchrun --nnodes "$SLURM_JOB_NUM_NODES" --nproc-per-node "$gpus_per_node" \
    --rdzv-backend c10d --rdzv-endpoint "$head_node:$port" --rdzv-id "bmimic-$SLURM_JOB_ID" \
    -m bmimic.train "hydra.run.dir=outputs/runs/\${run_name}/slurm-$SLURM_JOB_ID" "$@"
