#!/bin/bash
# The races of issue 44: all of dance1_subject1 (motion=lafan_dance1_full, env=tracking) to the whole-clip
# finish line (robust whole-clip success >= 0.90 and 0.95, judged live in native MuJoCo on the host's CPU
# cores), per GPU count, envs per GPU and sampler. One row is one race on one machine, alone:
#
#   bash sweeps/races_dance1_whole_clip.sh --list              # the rows, and which have a record
#   bash sweeps/races_dance1_whole_clip.sh ROW [--dry-run]     # race one row (needs its GPUs)
#
# Each race writes docs/bench/<date>_<card>_race_<row>.json (card: h100, h200, ... from nvidia-smi) and
# its run folder outputs/runs/race/<row>; `python -m analysis.races docs/bench/*_<card>_race_*.json --out
# docs/bench/race_curves_<card>` rebuilds the card's table and curves from the records. Launch cold or
# after a warm-up (WARMUP=1: ten iterations of the same shapes first, so start-up excludes compilation),
# and say which in the benchmarks.md section. The budget (BUDGET_S, default 1500 s) caps wall time from
# launch; a row whose thresholds are all reached stops sooner. Rows that share a GPU are never raced:
# the clock is the measurement.
#
# Two one-GPU rows may run at once on a 2-GPU machine, each alone on its GPU, the host's cores split between
# their judges (say so beside the times: the host is shared):
#   CUDA_VISIBLE_DEVICES=0 JUDGE_WORKERS=12 bash sweeps/races_dance1_whole_clip.sh 1x4096-hybrid-s1 &
#   CUDA_VISIBLE_DEVICES=1 JUDGE_WORKERS=12 bash sweeps/races_dance1_whole_clip.sh 1x8192-hybrid-s0
#
# Measured so far (docs/benchmarks.md): 2x4096-hybrid-s0 on 2 x H200, cold: 95% robust whole clip at 422 s;
# 1x4096-hybrid-s0 on one H200, cold: 90% at 607 s, 95% not held twice in 900 s (judged 0.906-0.969);
# 1x4096-hybrid-s1: 90% at 651 s, 95% not in 850 s; 1x4096-design-s0: 90% not in 865 s (judged 0.867 at it 2600);
# 1x4096-uniform-s0 (BUDGET_S=1480): no robust whole clip at all in 1483 s (0 of 128 at every judgement to it 4000).
# 1x8192-hybrid-s0, cold: 90% at 549 s, 95% at 697 s; 1x8192-hybrid-s1 (BUDGET_S=540, warm caches): 90% at 389 s.
# 1x8192-hybrid-s2: 90% at 431 s, 95% not in 810 s; 2x4096-hybrid-s1, cold: 90% at 389 s, 95% not in 654 s (judged
# 0.906-0.953 past it 1000: the 95% line is within noise of where the hybrid plateaus).
set -euo pipefail

# row: GPUs, envs per GPU, sampler, seed, and optionally one more Hydra override (a variant raced against the
# plain row of the same seed, both at once on a 2-GPU machine, one GPU each; the record
# 2026-12-01_h200_race_1x8192-hybrid-s2-overlap.json raced ppo.overlap_update=true of commit a23f2eb this way,
# an option since removed). 1x4096-uniform asks whether uniform ever finishes in 30 minutes
# (BUDGET_S=1800 for it where a machine can be held that long past staging; a lent machine's 30 minutes allowed
# 1480 s, the record of 2026-12-01).
ROWS="
1x4096-hybrid-s0   1 4096 adaptive_hybrid 0
1x4096-hybrid-s1   1 4096 adaptive_hybrid 1
1x8192-hybrid-s0   1 8192 adaptive_hybrid 0
1x8192-hybrid-s1   1 8192 adaptive_hybrid 1
1x8192-hybrid-s2   1 8192 adaptive_hybrid 2
1x4096-design-s0   1 4096 adaptive        0
1x4096-uniform-s0  1 4096 uniform         0
2x4096-hybrid-s0   2 4096 adaptive_hybrid 0
2x4096-hybrid-s1   2 4096 adaptive_hybrid 1
4x4096-hybrid-s0   4 4096 adaptive_hybrid 0
4x4096-hybrid-s1   4 4096 adaptive_hybrid 1
4x2048-hybrid-s0   4 2048 adaptive_hybrid 0
"
cd "$(dirname "$0")/.."

if [ "${1:-}" = "--list" ]; then
  echo "$ROWS" | while read -r row gpus envs sampler seed extra; do
    [ -n "$row" ] || continue
    done_as=$(ls docs/bench/*_race_"$row".json 2>/dev/null | tr '\n' ' ' || true)
    echo "$row gpus=$gpus num_envs_per_gpu=$envs sampler=$sampler seed=$seed ${extra:+$extra }${done_as:-(no record)}"
  done
  exit 0
fi

row=${1:?"usage: $0 --list | ROW [--dry-run]"}
spec=$(echo "$ROWS" | awk -v r="$row" '$1 == r {print $2, $3, $4, $5, $6}')
if [ -z "$spec" ]; then
  echo "error: no row '$row' in $0 (--list shows them)" >&2
  exit 2
fi
read -r gpus envs sampler seed extra <<< "$spec"
card=$( (nvidia-smi --query-gpu=name --format=csv,noheader 2>/dev/null || echo unknown) | sed -n 1p \
        | sed -E 's/^NVIDIA //; s/ .*//' | tr 'A-Z' 'a-z')
json="docs/bench/$(date +%F)_${card}_race_${row}.json"
run="outputs/runs/race/$row"
workers=${JUDGE_WORKERS:-$(( $(nproc) * 3 / 4 ))}  # the judge's CPU workers: the rest of the cores feed the GPUs
[ "$workers" -ge 1 ] || workers=1
overrides=(motion=lafan_dance1_full env=tracking "sampler=$sampler" "num_envs=$envs" "seed=$seed" progress_bar=false)
[ -z "$extra" ] || overrides+=("$extra")
race=(-m bmimic.race --native-whole-clip "$workers" --budget-s "${BUDGET_S:-1500}" --json "$json"
      "${overrides[@]}" "hydra.run.dir=$run")
if [ "$gpus" -gt 1 ]; then
  launcher=(torchrun --standalone --nproc_per_node "$gpus")
  warm=(torchrun --standalone --nproc_per_node "$gpus")
else
  launcher=(python)
  warm=(python)
fi
if [ "${2:-}" = "--dry-run" ]; then
  [ "${WARMUP:-0}" = 1 ] && echo "${warm[*]} -m bmimic.train ${overrides[*]} max_iterations=10 eval.every_iters=10 ppo.save_interval=10 hydra.run.dir=outputs/runs/race/warmup-$row"
  echo "${launcher[*]} ${race[*]}"
  exit 0
fi
export NCCL_NVLS_ENABLE=0  # NVLink multicast off (the GPU machines' notes)
if [ "${WARMUP:-0}" = 1 ]; then
  "${warm[@]}" -m bmimic.train "${overrides[@]}" max_iterations=10 eval.every_iters=10 \
    ppo.save_interval=10 "hydra.run.dir=outputs/runs/race/warmup-$row"
fi
"${launcher[@]}" "${race[@]}"
# The final policy's whole clips in MuJoCo-Warp too (nominal and robust, the same checkpoint the race's
# native judge evaluated last): race.json holds the native figure, this the simulator's. WARP_WHOLE_CLIP=0
# skips it (about two minutes of the machine) where that gap was already measured.
[ "${WARP_WHOLE_CLIP:-1}" = 0 ] && exit 0
python -m bmimic.eval "$run" --whole-clip 128 --conditions nominal,robust
