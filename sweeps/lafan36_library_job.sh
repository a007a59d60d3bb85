#!/bin/bash
# One job of the 36-clip library study (sweeps/lafan36_library.yaml, issue 45), trained sitting by sitting:
#
#   BMIMIC_LAFAN_DIR=/tmp/lafan36 bash sweeps/lafan36_library_job.sh ARM SEED [--dry-run]
#
# ARM: adaptive (the design), adaptive_hybrid, uniform, egm or gmt. Each call adds TRAIN_S seconds (default
# 1000) to the job's training time (time_limit_s counts the run's cumulative training time, read from its
# latest checkpoint), on NPROC GPUs (default 1; more: one torchrun run over them; keep a job's NPROC). The
# first call starts the job, later ones continue it (resume=true: the config is checked first, and the clips
# must sit at the same absolute path every sitting, since data.lafan_dir is compared). The job's folder is the
# multirun's, RUNS_ROOT/motion=lafan_folder,sampler=ARM/seed=SEED (RUNS_ROOT: outputs/sweeps/lafan36_library),
# so `python -m analysis.report RUNS_ROOT` reads the jobs as one study. ITERS (optional) pauses the job after
# that iteration (stop_at_iteration), to bring an arm to another arm's iterations: the arms are compared at
# equal iterations, and a later call without ITERS continues the job to the study's max_iterations (8400),
# which stays the job's recorded budget. (Jobs paused before stop_at_iteration existed had ITERS written as
# max_iterations; a later call sets it back to 8400, a change a resume accepts.) EGM's jobs also get the
# study's max_iterations as sampler.schedule_iterations in every call, as they always have, so its annealing
# spans the study whatever a sitting does. On a 2-GPU
# machine two jobs share a sitting, one per GPU (compared by iterations, never by wall time):
#   CUDA_VISIBLE_DEVICES=0 bash sweeps/lafan36_library_job.sh adaptive_hybrid 0 &
#   CUDA_VISIBLE_DEVICES=1 bash sweeps/lafan36_library_job.sh adaptive 0
# Measured (docs/benchmarks.md, 2026-11-30): one H200 at 8192 envs trains ~2,800 iterations per 1000 s.
set -euo pipefail
cd "$(dirname "$0")/.."

usage="usage: $0 ARM SEED [--dry-run]  (ARM: adaptive, adaptive_hybrid, uniform, egm, gmt)"
arm=${1:?$usage}
seed=${2:?$usage}
case "$arm" in adaptive|adaptive_hybrid|uniform|egm|gmt) ;; *) echo "error: unknown ARM '$arm'; $usage" >&2; exit 2;; esac
[[ "$seed" =~ ^[0-9]+$ ]] || { echo "error: SEED must be a whole number, got '$seed'" >&2; exit 2; }
dry=${3:-}
train_s=${TRAIN_S:-1000}
[[ "$train_s" =~ ^[0-9]+$ ]] && [ "$train_s" -gt 0 ] || { echo "error: TRAIN_S must be a positive whole number of seconds, got '$train_s'" >&2; exit 2; }
nproc=${NPROC:-1}
[[ "$nproc" =~ ^[1-9][0-9]*$ ]] || { echo "error: NPROC must be a positive whole number, got '$nproc'" >&2; exit 2; }
overrides=()
if [ "$arm" = egm ]; then  # the schedule spans the study's budget, whatever one sitting's ITERS says
  study_iters=$(sed -n 's/^max_iterations: *\([0-9][0-9]*\).*/\1/p' sweeps/lafan36_library.yaml)
  [ -n "$study_iters" ] || { echo "error: sweeps/lafan36_library.yaml: no top-level max_iterations for EGM's schedule" >&2; exit 2; }
  overrides=("sampler.schedule_iterations=$study_iters")
fi
if [ -n "${ITERS:-}" ]; then
  [[ "$ITERS" =~ ^[1-9][0-9]*$ ]] || { echo "error: ITERS must be a positive whole number of iterations, got '$ITERS'" >&2; exit 2; }
  overrides+=("stop_at_iteration=$ITERS")
fi
run="${RUNS_ROOT:-outputs/sweeps/lafan36_library}/motion=lafan_folder,sampler=$arm/seed=$seed"

# the training time the job has had (0 before its first checkpoint), read weights-only
done_s=0
if [ -f "$run/checkpoints/latest.pt" ]; then
  done_s=$(python -c "import sys, torch; print(int(torch.load(sys.argv[1], weights_only=True, map_location='cpu')['progress']['wall_time_s']))" \
           "$run/checkpoints/latest.pt")
  resume=(resume=true)
else
  resume=()
fi
args=(-m bmimic.train +sweep=lafan36_library "sampler=$arm" "seed=$seed" "hydra.run.dir='$run'" "${resume[@]}"
      "time_limit_s=$((done_s + train_s))" "${overrides[@]}" logger=none progress_bar=false)
if [ "$nproc" -gt 1 ]; then launcher=(torchrun --standalone --nproc_per_node "$nproc"); else launcher=(python); fi
if [ "$dry" = "--dry-run" ]; then
  printf '%q ' "${launcher[@]}" "${args[@]}" | sed 's/ $//'; echo  # shell-quoted: pastes back as these arguments
  exit 0
fi
[ -n "${BMIMIC_LAFAN_DIR:-}" ] && [ -d "$BMIMIC_LAFAN_DIR" ] || {
  echo "error: BMIMIC_LAFAN_DIR must name the folder of the 36 unpacked clips (lafan1_g1_36.tar.xz), got '${BMIMIC_LAFAN_DIR:-}'" >&2; exit 2; }
export NCCL_NVLS_ENABLE=0  # NVLink multicast off (the GPU machines' notes)
"${launcher[@]}" "${args[@]}"
