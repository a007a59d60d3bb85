"""One policy's success over the R rollouts of one evaluation: a binomial proportion and its interval.

A whole-clip judgement runs R rollouts of one checkpoint, each its own draw of the perturbations, so its
success is k of R Bernoulli draws. Wilson's score interval says how far that pins the policy down; it is an
interval over rollouts of one policy, never over seeds (analysis.stats draws those), and unlike p ± z·SE it
stays honest at 0 of R and R of R.
"""

from __future__ import annotations

import math
from statistics import NormalDist


def wilson_interval(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson's score interval of ``successes`` of ``trials`` Bernoulli draws at two-sided ``confidence``:
    the proportions p whose score test (p_hat - p) / sqrt(p (1 - p) / n) is within the normal quantile z."""
    if trials < 1 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials and trials >= 1, got {successes} of {trials}")
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    p, z2n = successes / trials, z * z / trials
    centre = (p + z2n / 2) / (1 + z2n)
    half = z * math.sqrt(p * (1 - p) / trials + z2n / (4 * trials)) / (1 + z2n)
    # at 0 (or all) successes the bound is exactly 0 (1): the formula leaves a rounding residue there
    return (0.0 if successes == 0 else centre - half), (1.0 if successes == trials else centre + half)
