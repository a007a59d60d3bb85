#!/bin/bash
# One sitting of a job of study `lafan36_whole` (issue 73): the 36-clip library trained to robust
# whole-clip success across sittings, each sitting's end committed to git so that the next one continues.
# The job is sweeps/lafan36_library.yaml's (same config, same job script); only its folders are new,
# since the earlier study's jobs died with their sittings (no checkpoint of theirs survived).
#
#   BMIMIC_LAFAN_DIR=/tmp/lafan36 bash sweeps/lafan36_whole_sitting.sh ARM SEED restore   # before training
#   BMIMIC_LAFAN_DIR=/tmp/lafan36 bash sweeps/lafan36_whole_sitting.sh ARM SEED train     # TRAIN_S more s
#   bash sweeps/lafan36_whole_sitting.sh ARM SEED save                                     # after, or any time
#   BMIMIC_LAFAN_DIR=/tmp/lafan36 bash sweeps/lafan36_whole_sitting.sh ARM SEED wholeclip # then save again
#
# restore: when the job has a committed state (STATE_DIR/ARM-sSEED.pt) and its run folder under RUNS_ROOT
#   holds no checkpoint yet, copy the job's committed record (RECORD_DIR/JOB) there and `bmimic.state
#   restore` the state into it. A first sitting has neither: training starts the job.
# train: sweeps/lafan36_library_job.sh ARM SEED with RUNS_ROOT (resume=true once a checkpoint exists).
# save: `bmimic.state save` the run's newest checkpoint to STATE_DIR/ARM-sSEED.pt (fp32 weights, Adam moments
#   in MOMENTS, default bf16; no worlds' state), and copy its record (no checkpoints, ONNX or log) to
#   RECORD_DIR/JOB compacted (analysis.compact). Commit both.
# wholeclip: the issue's measure of the newest checkpoint, robust whole clips (ROLLOUTS per clip, default 128),
#   into the run's eval/<checkpoint>/whole_clip/; a save after it carries them into the record.
# Defaults: RUNS_ROOT=outputs/sweeps/lafan36_whole, STATE_DIR=docs/results/lafan36_whole/state,
# RECORD_DIR=docs/results/lafan36_whole/runs. The clips must sit at the same absolute path every sitting
# (data.lafan_dir is compared on resume): unpack lafan1_g1_36.tar.xz to /tmp/lafan36 each time.
set -euo pipefail
cd "$(dirname "$0")/.."

usage="usage: $0 ARM SEED restore|train|save|wholeclip"
arm=${1:?$usage}
seed=${2:?$usage}
step=${3:?$usage}
case "$arm" in adaptive|adaptive_hybrid|uniform|egm|gmt) ;; *) echo "error: unknown ARM '$arm'; $usage" >&2; exit 2;; esac
[[ "$seed" =~ ^[0-9]+$ ]] || { echo "error: SEED must be a whole number, got '$seed'" >&2; exit 2; }
runs_root=${RUNS_ROOT:-outputs/sweeps/lafan36_whole}
state_dir=${STATE_DIR:-docs/results/lafan36_whole/state}
record_dir=${RECORD_DIR:-docs/results/lafan36_whole/runs}
job="motion=lafan_folder,sampler=$arm/seed=$seed"
run="$runs_root/$job"
state="$state_dir/$arm-s$seed.pt"

case "$step" in
  restore)
    if [ -e "$run/checkpoints/latest.pt" ]; then echo "$run: has a checkpoint; nothing to restore"; exit 0; fi
    if [ ! -f "$state" ]; then echo "$state: none yet; the first sitting starts the job"; exit 0; fi
    [ -d "$record_dir/$job" ] || { echo "error: $state has no record beside it ($record_dir/$job)" >&2; exit 2; }
    [ ! -e "$run" ] || { echo "error: $run exists without a checkpoint; move it away first" >&2; exit 2; }
    mkdir -p "$(dirname "$run")"
    cp -r "$record_dir/$job" "$run"
    python -m bmimic.state restore "$state" "$run" ;;
  train)
    RUNS_ROOT="$runs_root" bash sweeps/lafan36_library_job.sh "$arm" "$seed" ;;
  save)
    mkdir -p "$state_dir" "$record_dir/$job"
    python -m bmimic.state save "$run" "$state" --moments "${MOMENTS:-bf16}"
    tmp=$(mktemp -d)
    tar -C "$run" --exclude=checkpoints --exclude=.bmimic.lock --exclude=train.log -cf - . | tar -C "$tmp" -xf -
    python -m analysis.compact "$tmp"
    rm -rf "${record_dir:?}/$job" && mv "$tmp" "$record_dir/$job" ;;
  wholeclip)
    [ -e "$run/checkpoints/latest.pt" ] || { echo "error: $run has no checkpoint to evaluate" >&2; exit 2; }
    python -m bmimic.eval "$run" --whole-clip "${ROLLOUTS:-128}" --conditions robust ;;
  *) echo "error: unknown step '$step'; $usage" >&2; exit 2 ;;
esac
