"""Timing of the sampler hot path, for both update schedules of a named variant.

    python -m bmimic.sampling.benchmark --num-envs 16384 --num-bins 10000 --device cuda
    python -m bmimic.sampling.benchmark --sampler adaptive_hybrid      # update_every=step

prints one line with microseconds per call. Parts, each timed alone:

- ``count``: one control step's bookkeeping (:meth:`SamplerFeedback.count` of ~num_envs/50
  finished episodes into per-bin counts, then ``record``: a sampler update for
  ``update_every=step``, an add to the pending counts for ``update_every=iteration``);
- ``update``: one ``update_counts`` (the per-step update, or the one update after a rollout);
- ``end_rollout``: the per-iteration update as the trainer calls it (``update_every=iteration``);
- ``sample``: ``sample(num_envs)`` plus the start frames of the drawn bins, with both sampling
  methods (the default, inverse CDF, and ``torch.multinomial``);
- ``update_plus_sample``: ``update`` + ``sample`` (the figure docs/benchmarks.md tracks, < 1 ms at
  16k envs x 10k bins);
- ``iteration``: a whole rollout's sampler work per control step: ``steps_per_iteration`` x (count +
  record + sample) plus ``end_rollout``, divided by ``steps_per_iteration``.

For the samplers that learn from tracking errors (egm, gmt) ``count`` also sums the step's errors per
bin (:meth:`SamplerFeedback.measure`; computing them is the environment's, timed by ``bmimic.bench``)
and ``update`` also feeds one iteration's errors; for the ones that learn from evaluations (phc,
protomotions) ``observe_eval`` times one evaluation's update. ``--num-clips`` cuts the bins into that many equal clips (a library).

On CUDA the loops are timed with CUDA events (the host never waits inside them, as in training); on
CPU with ``time.perf_counter``. The test suite runs 10^4 sequential updates; the long-run stability
check of 10^6 updates is ``--iters 1000000``.
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import math
import time
from typing import Any, Callable

import torch

from bmimic.sampling.base import ERROR_COMPONENTS
from bmimic.sampling.config import layout_for, load_variant, make_sampler, variant_names
from bmimic.sampling.feedback import SamplerFeedback
from bmimic.sampling.signals import CLIP_OUTCOMES, TRACKING_ERRORS

FPS = 50.0
MAX_EPISODE_LENGTH = 500  # 10 s at 50 Hz, BeyondMimic's


def _time_per_call(fn: Callable[[], Any], iters: int, device: torch.device) -> float:
    """Mean seconds per call of ``fn`` after a short warm-up."""
    for _ in range(min(10, iters)):
        fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        for _ in range(iters):
            fn()
        end.record()
        torch.cuda.synchronize(device)
        return start.elapsed_time(end) / 1e3 / iters
    t0 = time.perf_counter()
    for _ in range(iters):
        fn()
    return (time.perf_counter() - t0) / iters


def _frames_for(bins: str, num_bins: int) -> int:
    """A motion length (frames at 50 fps) whose layout has ``num_bins`` bins."""
    return num_bins * int(FPS) if bins == "time" else (num_bins - 1) * int(FPS) + int(FPS) // 2


def bench_sampler(
    num_envs: int = 16384,
    num_bins: int = 10000,
    device: str = "cuda",
    iters: int = 1000,
    sampler: str = "adaptive",
    seed: int = 0,
    steps_per_iteration: int = 24,
    update_every: str | None = None,
    num_clips: int = 1,
) -> dict[str, Any]:
    """Time the sampler work of variant ``sampler`` (``conf/sampler/<sampler>.yaml``, with 1 s time
    bins or the released layout, ``update_every`` overridden when given) on ``device``.

    Each step's batch is fixed: about num_envs/50 finished episodes (50 Hz control, ~1 s episodes),
    10% of them terminated early. Returns microseconds per call of each part (see the module
    docstring) and a check that the probabilities stayed finite and normalised.
    """
    dev = torch.device(device)
    cfg = load_variant(sampler)
    if update_every is not None:
        cfg.accounting.update_every = update_every
    layout = layout_for(cfg, _frames_for(cfg.bins, num_bins), FPS, device=dev)
    s = make_sampler(cfg, layout.num_bins, dev)
    if num_clips > 1:
        bin_clip = torch.arange(layout.num_bins, device=dev) * num_clips // layout.num_bins
        last = torch.zeros(num_clips, dtype=torch.long, device=dev).scatter_reduce(
            0, bin_clip, torch.arange(layout.num_bins, device=dev), "amax")
        s.set_clips(bin_clip, last[bin_clip], num_clips)
    acc = SamplerFeedback.from_config(cfg.accounting, s, layout, num_envs, MAX_EPISODE_LENGTH, device=dev)
    gen = torch.Generator(device=dev).manual_seed(seed)
    n = layout.num_frames
    dones = torch.rand(num_envs, generator=gen, device=dev) < 1.0 / FPS
    terminated = dones & (torch.rand(num_envs, generator=gen, device=dev) < 0.1)
    never = torch.zeros_like(dones)
    segment_start = torch.randint(0, n, (num_envs,), generator=gen, device=dev)
    end_frames = torch.clamp(segment_start + int(FPS), max=n - 1)
    length = torch.randint(0, MAX_EPISODE_LENGTH, (num_envs,), generator=gen, device=dev)
    acc.start_episodes(~never, layout.bins_of(segment_start))
    counts = acc.count(dones, never, end_frames, segment_start, terminated, never, length)
    step_errors = torch.rand(len(ERROR_COMPONENTS), num_envs, generator=gen, device=dev)
    rewards = torch.rand(num_envs, generator=gen, device=dev)
    error_sums = torch.rand(len(ERROR_COMPONENTS), layout.num_bins, generator=gen, device=dev, dtype=torch.float64)
    error_steps = torch.ones(layout.num_bins, device=dev, dtype=torch.float64)
    clip_failed = torch.rand(max(num_clips, 1), generator=gen, device=dev) < 0.5

    def count() -> None:
        acc.measure(segment_start, never, dones, rewards, lambda: step_errors)
        acc.record(acc.count(dones, never, end_frames, segment_start, terminated, never, length))

    def update() -> None:
        s.update_counts(counts[0], counts[1])
        if TRACKING_ERRORS in s.signals:
            s.update_errors(error_sums, error_steps)

    def sample() -> None:
        layout.sample_frames(s.sample(num_envs, generator=gen), generator=gen)

    def rollout() -> None:
        for _ in range(steps_per_iteration):
            count()
            sample()
        acc.end_rollout()

    def us(fn: Callable[[], Any], calls: int = iters) -> float:
        return 1e6 * _time_per_call(fn, calls, dev)

    result: dict[str, Any] = {
        "sampler": sampler,
        "update_every": cfg.accounting.update_every,
        "device": str(dev),
        "num_envs": num_envs,
        "num_bins": layout.num_bins,
        "num_clips": num_clips,
        "iters": iters,
        "method": s.method,
        "count_us": us(count),
        "update_us": us(update),
        "end_rollout_us": us(acc.end_rollout),
        "iteration_us": us(rollout, max(1, iters // steps_per_iteration)) / steps_per_iteration,
    }
    if CLIP_OUTCOMES in s.signals:
        result["observe_eval_us"] = us(lambda: s.observe_eval(clip_failed, 200))
    for method in ("multinomial", "inverse_cdf"):
        s.method = method
        result[f"sample_{method}_us"] = us(sample)
    s.method = "inverse_cdf"
    result["update_plus_sample_us"] = result["update_us"] + result["sample_inverse_cdf_us"]
    p = s.probabilities()
    result["probs_ok"] = bool(torch.isfinite(p).all()) and math.isclose(float(p.sum()), 1.0, abs_tol=1e-9)
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=16384)
    parser.add_argument("--num-bins", type=int, default=10000)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--iters", type=int, default=1000)
    parser.add_argument("--sampler", default="adaptive", choices=list(variant_names()))
    parser.add_argument("--update-every", default=None, choices=["step", "iteration"],
                        help="override the variant's sampler.accounting.update_every")
    parser.add_argument("--steps-per-iteration", type=int, default=24)
    parser.add_argument("--num-clips", type=int, default=1, help="cut the bins into this many equal clips")
    args = parser.parse_args(argv)
    r = bench_sampler(args.num_envs, args.num_bins, args.device, args.iters, args.sampler,
                      steps_per_iteration=args.steps_per_iteration, update_every=args.update_every,
                      num_clips=args.num_clips)
    print(
        f"{r['sampler']} (update_every={r['update_every']}) on {r['device']}: num_envs={r['num_envs']} "
        f"num_bins={r['num_bins']} iters={r['iters']} method={r['method']} "
        f"update+sample={r['update_plus_sample_us']:.1f}us update={r['update_us']:.1f}us "
        f"count={r['count_us']:.1f}us end_rollout={r['end_rollout_us']:.1f}us "
        f"sample: inverse_cdf={r['sample_inverse_cdf_us']:.1f}us multinomial={r['sample_multinomial_us']:.1f}us "
        f"iteration/step={r['iteration_us']:.1f}us probs_ok={r['probs_ok']}"
        + (f" observe_eval={r['observe_eval_us']:.1f}us" if "observe_eval_us" in r else "")
        + (f" num_clips={r['num_clips']}" if r["num_clips"] > 1 else "")
    )


if __name__ == "__main__":
    main()
