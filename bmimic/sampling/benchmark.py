"""Timing of the sampler hot path: one ``update_counts`` plus one ``sample(num_envs)`` per step.

    python -m bmimic.sampling.benchmark --num-envs 16384 --num-bins 10000 --device cuda

prints one line with microseconds per step. On CUDA the loop is timed with CUDA events (the
host never waits inside it, as in training); on CPU with ``time.perf_counter``. The same
probabilities are also sampled with the other method (multinomial vs inverse CDF) so the choice
of the default (inverse CDF) can be checked on the machine at hand. The test suite runs 10^4
sequential updates; the long-run stability check of 10^6 updates is ``--iters 1000000``.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any, Callable

import torch

from bmimic.sampling.config import SamplerConfig, make_sampler


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


def bench_sampler(
    num_envs: int = 16384,
    num_bins: int = 10000,
    device: str = "cuda",
    iters: int = 1000,
    sampler: str = "adaptive",
    seed: int = 0,
) -> dict[str, Any]:
    """Time ``update_counts`` + ``sample(num_envs)`` of ``sampler`` (a config name) on ``device``.

    Each step feeds counts of a fixed random batch (about num_envs/50 finished episodes, a 10%
    failure rate, as at a 50 Hz control rate with ~1 s episodes). Returns microseconds per step
    for the pair and for each part, the sampling time of both sampling methods, and a check that
    the probabilities stayed finite and normalised.
    """
    dev = torch.device(device)
    cfg = SamplerConfig(name=sampler, K=3, gamma=0.8)
    s = make_sampler(cfg, num_bins, dev)
    gen = torch.Generator(device=dev).manual_seed(seed)
    finished = max(1, num_envs // 50)
    bins = torch.randint(0, num_bins, (finished,), generator=gen, device=dev)
    failed = torch.rand(finished, generator=gen, device=dev) < 0.1
    episodes = torch.zeros(num_bins, device=dev).index_add_(0, bins, torch.ones(finished, device=dev))
    failures = torch.zeros(num_bins, device=dev).index_add_(0, bins, failed.float())

    def step() -> None:
        s.update_counts(episodes, failures)
        s.sample(num_envs, generator=gen)

    result: dict[str, Any] = {
        "sampler": sampler,
        "device": str(dev),
        "num_envs": num_envs,
        "num_bins": num_bins,
        "iters": iters,
        "method": s.method,
        "step_us": 1e6 * _time_per_call(step, iters, dev),
        "update_us": 1e6 * _time_per_call(lambda: s.update_counts(episodes, failures), iters, dev),
    }
    for method in ("multinomial", "inverse_cdf"):
        s.method = method
        result[f"sample_{method}_us"] = 1e6 * _time_per_call(
            lambda: s.sample(num_envs, generator=gen), iters, dev
        )
    p = s.probabilities()
    result["probs_ok"] = bool(torch.isfinite(p).all()) and math.isclose(float(p.sum()), 1.0, abs_tol=1e-9)
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=16384)
    parser.add_argument("--num-bins", type=int, default=10000)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--iters", type=int, default=1000)
    parser.add_argument("--sampler", default="adaptive", choices=["uniform", "adaptive", "beyondmimic"])
    args = parser.parse_args(argv)
    r = bench_sampler(args.num_envs, args.num_bins, args.device, args.iters, args.sampler)
    print(
        f"{r['sampler']} on {r['device']}: num_envs={r['num_envs']} num_bins={r['num_bins']} iters={r['iters']} "
        f"method={r['method']} step={r['step_us']:.1f}us update_counts={r['update_us']:.1f}us "
        f"sample: multinomial={r['sample_multinomial_us']:.1f}us inverse_cdf={r['sample_inverse_cdf_us']:.1f}us "
        f"probs_ok={r['probs_ok']}"
    )


if __name__ == "__main__":
    main()
