#!/usr/bin/env bash
# The first GPU result (docs/results/): the sampler_ablation arms (uniform vs adaptive_hybrid, called
# adaptive when the result was made) on the embedded default motion and on a 60 s window of LAFAN1
# dance1_subject1, all jobs at once on one GPU. That result used 3 seeds and a wall-clock budget
# (time_limit_s=660); this script now gives every job the same iteration budget (max_iterations):
# jobs sharing a GPU complete unequal numbers of iterations in the same wall time, so a wall-clock
# budget compares the GPU scheduler as much as the arms. 5 seeds per arm, the fewest for which
# analysis.report draws bootstrap intervals. Same layout as `python -m bmimic.train -m ...`
# (outputs/sweeps/<name>/<arm>/seed=<s>/).
#
#   ITERS=500 ENVS=2048 bash docs/results/run_first_result.sh
# motion=lafan_dance1 reads dance1_subject1.csv from $BMIMIC_LAFAN_DIR (the LAFAN1 G1 folder; README: Data).
#   python -m analysis.report outputs/sweeps/first_default outputs/... (see docs/results/README)
set -u
ITERS=${ITERS:-500}          # PPO iterations per job
ENVS=${ENVS:-2048}           # worlds per job
SEEDS=${SEEDS:-"0 1 2 3 4"}
MOTIONS=${MOTIONS:-"default lafan_dance1"}
NGPU=${NGPU:-1}              # motion k runs on GPU k mod NGPU
EXTRA=${EXTRA:-}             # further overrides for every job, e.g. an MDP change
NAME=${NAME:-first}          # sweep folders are outputs/sweeps/${NAME}_<motion>
mkdir -p outputs/logs
k=0
for motion in $MOTIONS; do
  gpu=$((k % NGPU)); k=$((k + 1))
  for sampler in uniform adaptive_hybrid; do
    for seed in $SEEDS; do
      args=(-m "sampler=$sampler" "seed=$seed" "sweep_name=${NAME}_$motion" "num_envs=$ENVS"
            "max_iterations=$ITERS" "logger=none" "progress_bar=false"
            "eval.every_iters=25" "ppo.save_interval=100")
      [ "$motion" != default ] && args+=("motion=$motion")
      args+=($EXTRA)
      CUDA_VISIBLE_DEVICES=$gpu python3 -m bmimic.train "${args[@]}" > "outputs/logs/${motion}_${sampler}_${seed}.log" 2>&1 &
    done
  done
done
wait
