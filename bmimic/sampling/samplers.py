r"""Samplers that choose the bin each episode starts in.

A motion is cut into S bins (see :mod:`bmimic.sampling.bins` for the layouts). A sampler keeps a distribution P
over the bins, draws start bins from it and updates it from the outcome of finished episodes.
All samplers share one interface::

    s.update(bins, failed, visits=None)   # one batch of finished episodes
    s.update_counts(episodes, failures)   # the same from per-bin counts, no host synchronisation
    p = s.probabilities()                 # Tensor[S], >= 0, sums to 1
    b = s.sample(n, generator=None)       # LongTensor[n]
    s.state_dict(); s.load_state_dict(d)

For a batch, :math:`n_s` is the number of episodes charged to bin s (or, with ``visits``, the
number that were active in bin s) and :math:`f_s` the number of failed ones among them.

Look-ahead kernel (shared by both adaptive samplers). With kernel length K and decay
:math:`\gamma`, :math:`k_u = \gamma^u / \sum_{v=0}^{K-1} \gamma^v`, and for a vector x over bins

.. math:: (\mathcal{K} x)_s = \sum_{u=0}^{K-1} k_u \, x_{\min(s+u,\, S-1)}.

A bin is boosted by failures in the K-1 bins after it, so episodes start shortly *before* the
hard part; the right end is padded by repeating the last bin.

Each sampler's config schema (its defaults and range rules) sits above its class, which registers
with it (`register_sampler`) and whose constructor takes the validated schema instance; torch is bound
on first use, so composing a config imports this module without it. Adding a sampler is a schema and
a class here and a YAML in ``conf/sampler/`` (:mod:`bmimic.sampling.registry` shows the pattern).

**UniformSampler**: :math:`P_s = 1/S`; updates are ignored.

**AdaptiveSampler** (the design: BeyondMimic section III-F as written up in the project's design
notes). A smoothed failure rate r (initially 0) is updated from each batch's raw rates:

.. math::
    \mathrm{raw}_s = f_s / \max(n_s, 1),\qquad
    r_s \leftarrow \alpha_{smooth}\, \mathrm{raw}_s + (1-\alpha_{smooth})\, r_s,\qquad
    c = \mathcal{K} r,\qquad
    p_s = c_s / \textstyle\sum_j c_j \ \ (\text{uniform while } \sum_j c_j = 0),\qquad
    P_s = \lambda_{uniform}/S + (1-\lambda_{uniform})\, p_s .

With ``empty_bins="decay"`` (the design's formula) every bin is updated, so a bin without episodes
in the batch decays towards 0; with ``empty_bins="hold"`` only bins with :math:`n_s > 0` move and the
others keep their rate. :math:`P_s \ge \lambda_{uniform}/S` always: a true uniform floor.

**BeyondMimicSampler** (semantics of the released HybridRobotics/whole_body_tracking code). Every
update, including one with no finished episodes, decays an EMA of failure *counts* (not rates):

.. math::
    q \leftarrow \alpha\, f + (1-\alpha)\, q,\qquad
    w = \mathcal{K}\,(q + \epsilon/S),\qquad P = w / \textstyle\sum_j w_j,

with :math:`\epsilon` = ``uniform_ratio`` (``empty_bins="hold"`` would keep q where the batch has
no episodes; the released code decays every bin). Because q is a count, the weight of the uniform term,
:math:`\epsilon / (\sum_j q_j + \epsilon)`, depends on the number of environments and on how often
the policy fails; it is not a floor. The released code updates once per control step and draws
the resets of a step *before* adding that step's failures.

**LowReturnSampler** (``low_return``; the feedback protocol's worked example, issue 34). With
:math:`\bar R_s` an iteration's mean return of the episodes that started in bin s and finished,
:math:`R_s \leftarrow (1-\beta) R_s + \beta \bar R_s` (the first visit sets it; unvisited bins
hold); a bin never visited counts as the lowest visited one (so it is tried), and

.. math:: P_s = \lambda_{uniform}/S + (1-\lambda_{uniform})\, e^{-R_s/T} / \textstyle\sum_j e^{-R_j/T}

(uniform before any episode finished).

Sampling is exact inverse-CDF sampling: uniforms in [0, 1) are located with ``searchsorted`` in
the cumulative sum of P, which is cached at each update, so a draw is two kernels and never
synchronises with the host. ``torch.multinomial`` with replacement rebuilds its table on every
call and is the slower of the two on a GPU; ``method="multinomial"`` is kept for comparison
(:mod:`bmimic.sampling.benchmark` times both; the figures are in docs/benchmarks.md, "sampler alone").

``update_counts`` and ``sample`` write their cached tensors in place, use no data-dependent
shapes and never read values on the host, so the pair can be captured in a CUDA graph (eager, the
update is launch-bound: a few short kernels per control step).

State and probabilities are kept in float64 so that long runs (10^6 updates at alpha=0.001)
accumulate no visible rounding error; the cost is negligible at S <= 10^4.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional, TypeVar

from bmimic.cli.deferred import import_on_first_use
from bmimic.sampling.base import BinSampler
from bmimic.sampling.checks import check_choice, check_fraction, check_int_at_least, check_positive
from bmimic.sampling.registry import register_sampler
from bmimic.sampling.schemas import SamplerConfig
from bmimic.sampling.signals import EPISODE_OUTCOMES, EPISODE_RETURNS

if TYPE_CHECKING:
    import torch
else:
    torch = import_on_first_use("torch", globals())  # composing a config imports this module, not torch

EMPTY_BINS = ("decay", "hold")
"""`empty_bins` of the look-ahead samplers (adaptive, beyondmimic)."""


def lookahead_kernel(gamma: float, K: int, dtype: torch.dtype | None = None, device: torch.device | str = "cpu") -> torch.Tensor:
    """Normalised kernel k_u = gamma^u / sum_v gamma^v, u = 0..K-1 (float64 unless `dtype`)."""
    k = torch.tensor([gamma**u for u in range(K)], dtype=dtype or torch.float64, device=device)
    return k / k.sum()


def lookahead_index(num_bins: int, K: int, device: torch.device | str = "cpu", last: torch.Tensor | None = None) -> torch.Tensor:
    """Index table [S, K] with entry (s, u) = min(s + u, S - 1) (right end padded by replication); with
    ``last`` (LongTensor[S], the last bin of each bin's clip in a library) min(s + u, last[s]), so the
    kernel never reads across a clip boundary."""
    s = torch.arange(num_bins, device=device)[:, None]
    u = torch.arange(K, device=device)[None, :]
    if last is None:
        return (s + u).clamp_(max=num_bins - 1)
    return torch.minimum(s + u, torch.as_tensor(last, device=device).long()[:, None])


@dataclass
class UniformConfig(SamplerConfig):
    """`sampler=uniform`: no parameters of its own."""

    name: str = "uniform"
    kind: str = "uniform"


@register_sampler("uniform", UniformConfig)
class UniformSampler(BinSampler[UniformConfig]):
    """P_s = 1/S; updates are accepted and ignored."""

    def smoothed_failure(self) -> torch.Tensor:
        return torch.full((self.num_bins,), float("nan"), dtype=torch.float64, device=self.device)


@dataclass
class AdaptiveConfig(SamplerConfig):
    """Schema of the adaptive sampler's variants; the defaults are the design's (`sampler=adaptive`)."""

    name: str = "adaptive"
    kind: str = "adaptive"
    gamma: float = 0.9
    """Decay of the look-ahead kernel gamma^u, u = 0..K-1, in (0, 1]."""
    lambda_uniform: float = 0.1
    """Share of probability mass spread uniformly, in [0, 1]; P_s >= lambda_uniform/S."""
    K: int = 5
    """Length of the look-ahead kernel in bins (1 = no smoothing across bins)."""
    alpha_smooth: float = 0.1
    """EMA weight of a new failure-rate observation, in (0, 1]."""
    empty_bins: str = "decay"
    """"decay": every update moves every bin (a bin without finished episodes decays towards 0, the
    design's formula); "hold": bins without finished episodes keep their value."""

    def check(self) -> None:
        _check_lookahead(self)
        check_fraction("lambda_uniform", self.lambda_uniform, closed_below=True)
        check_fraction("alpha_smooth", self.alpha_smooth)


@dataclass
class BeyondMimicConfig(SamplerConfig):
    """Schema of the released code's sampler; the defaults are the released code's."""

    name: str = "beyondmimic"
    kind: str = "beyondmimic"
    bins: str = "released"
    bin_size_seconds: Optional[float] = None
    gamma: float = 0.8
    """Decay of the look-ahead kernel gamma^u, u = 0..K-1, in (0, 1]."""
    K: int = 1
    """Length of the look-ahead kernel in bins (1 = no smoothing across bins)."""
    alpha: float = 0.001
    """EMA weight of each update's failure histogram, in (0, 1]."""
    uniform_ratio: float = 0.1
    """uniform_ratio/S is added to the EMA counts before smoothing (> 0)."""
    empty_bins: str = "decay"
    """"decay": every update decays every bin (the released code); "hold": bins without finished
    episodes keep their value."""

    def check(self) -> None:
        _check_lookahead(self)
        check_fraction("alpha", self.alpha)
        check_positive("uniform_ratio", self.uniform_ratio)


MAX_LOOKAHEAD_BINS = 1000
"""The largest K: the kernel is a [bins, K] table on the device (8,018 bins x 1000 = 64 MB), and K=1e9
hung a run building it (issue 77's second round)."""


def _check_lookahead(cfg: AdaptiveConfig | BeyondMimicConfig) -> None:
    """The look-ahead kernel's keys, which the adaptive and beyondmimic schemas share (with their own defaults)."""
    check_fraction("gamma", cfg.gamma)
    check_int_at_least("K", cfg.K, 1, MAX_LOOKAHEAD_BINS)
    check_choice("empty_bins", cfg.empty_bins, EMPTY_BINS)


LookaheadConfigT = TypeVar("LookaheadConfigT", bound="AdaptiveConfig | BeyondMimicConfig")


class _LookaheadSampler(BinSampler[LookaheadConfigT]):
    """A sampler whose weights are smoothed with the look-ahead kernel and whose state is an EMA."""

    signals = (EPISODE_OUTCOMES,)

    def __init__(self, num_bins: int, cfg: LookaheadConfigT | None, device: torch.device | str, method: str):
        super().__init__(num_bins, cfg, device=device, method=method)
        self.gamma = float(self.cfg.gamma)
        self.K = int(self.cfg.K)
        self.empty_bins = str(self.cfg.empty_bins)
        self._kernel = lookahead_kernel(self.gamma, self.K, device=self.device)
        self._index = lookahead_index(num_bins, self.K, device=self.device)

    def set_clips(self, bin_clip: torch.Tensor, bin_last_in_clip: torch.Tensor, num_clips: int,
                  clip_balance: str = "bins", clip_weights: Any = None) -> None:
        """As BinSampler's; also stops the look-ahead kernel at each clip's last bin."""
        self._index = lookahead_index(self.num_bins, self.K, device=self.device, last=bin_last_in_clip)
        super().set_clips(bin_clip, bin_last_in_clip, num_clips, clip_balance, clip_weights)

    def _smooth(self, x: torch.Tensor) -> torch.Tensor:
        if self.K == 1:
            return x
        return x[self._index] @ self._kernel

    def _ema(self, state: torch.Tensor, target: torch.Tensor, episodes: torch.Tensor, weight: float) -> None:
        """state <- weight * target + (1 - weight) * state in place; with empty_bins="hold" bins
        without episodes lerp towards their own value, i.e. stay exactly unchanged."""
        if self.empty_bins == "hold":
            target = torch.where(episodes > 0, target, state)
        state.lerp_(target, weight)


@register_sampler("adaptive", AdaptiveConfig)
class AdaptiveSampler(_LookaheadSampler[AdaptiveConfig]):
    """The design: EMA of per-bin failure rates, look-ahead kernel, uniform mixture (see module doc);
    its parameters and their defaults (the design's): :class:`AdaptiveConfig`."""

    def __init__(self, num_bins: int, cfg: AdaptiveConfig | None = None, device: torch.device | str = "cpu",
                 method: str = "inverse_cdf"):
        super().__init__(num_bins, cfg, device, method)
        self.lambda_uniform = float(self.cfg.lambda_uniform)
        self.alpha_smooth = float(self.cfg.alpha_smooth)
        self._rate = torch.zeros(num_bins, dtype=torch.float64, device=self.device)

    def _update(self, episodes: torch.Tensor, failures: torch.Tensor) -> None:
        self._ema(self._rate, failures / episodes.clamp(min=1.0), episodes, self.alpha_smooth)
        self._recompute()

    def _recompute(self) -> None:
        c = self._smooth(self._rate)
        total = c.sum()
        # p = c / sum(c), or uniform while sum(c) == 0 (no failure seen yet); branch-free (the
        # 0/0 of the unselected branch is discarded).
        p = torch.where(total > 0, c / total, 1.0 / self.num_bins)
        torch.mul(p, 1.0 - self.lambda_uniform, out=self._probs).add_(self.lambda_uniform / self.num_bins)
        self._refresh_cdf()

    def smoothed_failure(self) -> torch.Tensor:
        """The smoothed failure rate r."""
        return self._rate.clone()

    def hparams(self) -> dict[str, Any]:
        return {
            "gamma": self.gamma,
            "lambda_uniform": self.lambda_uniform,
            "K": self.K,
            "alpha_smooth": self.alpha_smooth,
            "empty_bins": self.empty_bins,
        }

    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return {"rate": self._rate}


@register_sampler("beyondmimic", BeyondMimicConfig)
class BeyondMimicSampler(_LookaheadSampler[BeyondMimicConfig]):
    """Released-code form: EMA of failure counts plus uniform_ratio/S, look-ahead kernel (see module doc);
    its parameters and their defaults (the released code's, HybridRobotics/whole_body_tracking
    ``MotionCommandCfg``): :class:`BeyondMimicConfig`."""

    def __init__(self, num_bins: int, cfg: BeyondMimicConfig | None = None, device: torch.device | str = "cpu",
                 method: str = "inverse_cdf"):
        super().__init__(num_bins, cfg, device, method)
        self.alpha = float(self.cfg.alpha)
        self.uniform_ratio = float(self.cfg.uniform_ratio)
        self._count = torch.zeros(num_bins, dtype=torch.float64, device=self.device)
        self._recompute()

    def _update(self, episodes: torch.Tensor, failures: torch.Tensor) -> None:
        # With empty_bins="decay" (the released code) every call decays q, also when no episode
        # finished (failures all zero).
        self._ema(self._count, failures, episodes, self.alpha)
        self._recompute()

    def _recompute(self) -> None:
        w = self._smooth(self._count + self.uniform_ratio / self.num_bins)
        torch.div(w, w.sum(), out=self._probs)
        self._refresh_cdf()

    def smoothed_failure(self) -> torch.Tensor:
        """The EMA of failure counts q (scales with the number of environments)."""
        return self._count.clone()

    def hparams(self) -> dict[str, Any]:
        return {"gamma": self.gamma, "K": self.K, "alpha": self.alpha, "uniform_ratio": self.uniform_ratio,
                "empty_bins": self.empty_bins}

    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return {"count": self._count}


@dataclass
class LowReturnConfig(SamplerConfig):
    """`sampler=low_return`: start where episodes earn least (the per-bin mean episode return)."""

    name: str = "low_return"
    kind: str = "low_return"
    ema: float = 0.1
    """EMA weight of an iteration's mean return of the episodes started in a bin, in (0, 1]."""
    temperature: float = 1.0
    """Softmax temperature over the negated mean returns (return units), > 0: low = sharp."""
    lambda_uniform: float = 0.1
    """Share of probability mass spread uniformly, in [0, 1]."""

    def check(self) -> None:
        check_fraction("ema", self.ema)
        check_positive("temperature", self.temperature)
        check_fraction("lambda_uniform", self.lambda_uniform, closed_below=True)


@register_sampler("low_return", LowReturnConfig)
class LowReturnSampler(BinSampler[LowReturnConfig]):
    """Softmax over the negated EMA of each bin's mean episode return, with a uniform share (module doc)."""

    signals = (EPISODE_RETURNS,)

    def __init__(self, num_bins: int, cfg: LowReturnConfig | None = None, device: torch.device | str = "cpu",
                 method: str = "inverse_cdf"):
        super().__init__(num_bins, cfg, device, method)
        self.ema, self.temperature = float(self.cfg.ema), float(self.cfg.temperature)
        self.lambda_uniform = float(self.cfg.lambda_uniform)
        self._return = torch.zeros(num_bins, dtype=torch.float64, device=self.device)
        self._seen = torch.zeros(num_bins, dtype=torch.bool, device=self.device)

    def update_returns(self, sums: torch.Tensor, episodes: torch.Tensor) -> None:
        """One iteration's summed returns [1, S] of the episodes finished per start bin, and their number [S]."""
        visited = episodes > 0
        mean = sums[0].to(torch.float64) / episodes.to(torch.float64).clamp(min=1.0)
        self._return.copy_(torch.where(visited, torch.where(self._seen, self._return.lerp(mean, self.ema), mean),
                                       self._return))
        self._seen |= visited
        self._recompute()

    def _recompute(self) -> None:
        # An unvisited bin counts as the lowest visited one; before any visit every bin is 0 (uniform).
        lowest = torch.where(self._seen, self._return, torch.inf).amin()
        r = torch.where(self._seen, self._return, torch.where(self._seen.any(), lowest, 0.0))
        p = torch.softmax(-r / self.temperature, 0)
        torch.add(p * (1.0 - self.lambda_uniform), self.lambda_uniform / self.num_bins, out=self._probs)
        self._refresh_cdf()

    def smoothed_failure(self) -> torch.Tensor:
        """The EMA of each bin's mean episode return R (not a failure rate)."""
        return self._return.clone()

    def hparams(self) -> dict[str, Any]:
        return {"ema": self.ema, "temperature": self.temperature, "lambda_uniform": self.lambda_uniform}

    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return {"return": self._return, "seen": self._seen}


__all__ = ["EMPTY_BINS", "AdaptiveConfig", "AdaptiveSampler", "BeyondMimicConfig", "BeyondMimicSampler", "LowReturnConfig",
           "LowReturnSampler", "UniformConfig", "UniformSampler", "lookahead_index", "lookahead_kernel"]
