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

Sampling is exact inverse-CDF sampling: uniforms in [0, 1) are located with ``searchsorted`` in
the cumulative sum of P, which is cached at each update, so a draw is two kernels and never
synchronises with the host. ``torch.multinomial`` with replacement rebuilds its table on every
call; on an H200 it took 35-47 us against 21-31 us for the inverse CDF (4096-16384 draws,
240-10^4 bins). On a 2-core CPU the two are within noise of each other (about 1.4-1.7 ms for
16384 draws over 10^4 bins). ``method="multinomial"`` is kept for comparison
(:mod:`bmimic.sampling.benchmark` times both).

``update_counts`` and ``sample`` write their cached tensors in place, use no data-dependent
shapes and never read values on the host, so the pair can be captured in a CUDA graph (on an
H200: about 200 us eager, launch-bound at ~9 us a kernel, versus 25-45 us replayed).

State and probabilities are kept in float64 so that long runs (10^6 updates at alpha=0.001)
accumulate no visible rounding error; the cost is negligible at S <= 10^4.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from bmimic import BmimicError


class SamplerConfigError(BmimicError, ValueError):
    """A sampler option, or a sampler input that depends on one, is invalid."""


_DTYPE = torch.float64
_METHODS = ("inverse_cdf", "multinomial")
EMPTY_BINS = ("decay", "hold")


# Range checks. Each sampler class checks the keys it reads (``check_config``), the constructors
# call the same functions, so a bad value gets the same one-line message whichever way it arrives.
# Comparisons are written `not (lo < x <= hi)` so that NaN fails them.
def fail(key: str, rule: str, value: Any) -> None:
    """Raise SamplerConfigError("sampler.<key> must be <rule>, got <value>")."""
    raise SamplerConfigError(f"sampler.{key} must be {rule}, got {value!r}")


def is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def check_fraction(key: str, x: Any, closed_below: bool = False) -> None:
    """x in (0, 1] (or [0, 1] with closed_below)."""
    ok = is_number(x) and (0.0 <= x <= 1.0 if closed_below else 0.0 < x <= 1.0)
    if not ok:
        fail(key, "in [0, 1]" if closed_below else "in (0, 1]", x)


def check_choice(key: str, x: Any, choices: tuple[str, ...]) -> None:
    if x not in choices:
        fail(key, f"one of {', '.join(choices)}", x)


def check_K(K: Any) -> None:
    if not (isinstance(K, int) and not isinstance(K, bool) and K >= 1):
        fail("K", "an integer >= 1", K)


def check_uniform_ratio(uniform_ratio: Any) -> None:
    if not (is_number(uniform_ratio) and 0.0 < uniform_ratio < math.inf):
        fail("uniform_ratio", "a finite number > 0", uniform_ratio)



def lookahead_kernel(gamma: float, K: int, dtype: torch.dtype = _DTYPE, device: Any = "cpu") -> torch.Tensor:
    """Normalised kernel k_u = gamma^u / sum_v gamma^v, u = 0..K-1."""
    k = torch.tensor([gamma**u for u in range(K)], dtype=dtype, device=device)
    return k / k.sum()


def lookahead_index(num_bins: int, K: int, device: Any = "cpu") -> torch.Tensor:
    """Index table [S, K] with entry (s, u) = min(s + u, S - 1) (right end padded by replication)."""
    s = torch.arange(num_bins, device=device)[:, None]
    u = torch.arange(K, device=device)[None, :]
    return (s + u).clamp_(max=num_bins - 1)


def bin_counts(bins: torch.Tensor, num_bins: int, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Histogram of ``bins`` over ``num_bins`` bins (optionally weighted), as a fixed-size tensor.

    Unlike ``torch.bincount`` it never reads the data to size its output, so it does not
    synchronise a CUDA device with the host. Integer weights are summed in float32 and
    returned in their own dtype (long without weights): exact below 2**24 per bin, and compiled into a
    plain atomic add, where an int64 ``index_add_`` becomes a sort-based scatter.
    """
    if weights is None:
        weights = torch.ones_like(bins, dtype=torch.long)
    if weights.dtype.is_floating_point:
        return torch.zeros(num_bins, dtype=weights.dtype, device=bins.device).index_add_(0, bins, weights)
    out = torch.zeros(num_bins, dtype=torch.float32, device=bins.device).index_add_(0, bins, weights.float())
    return out.to(weights.dtype)


class _BinSampler:
    """Shared plumbing: cached probabilities and CDF, sampling, update(), state dict."""

    kind = ""

    @classmethod
    def check_config(cls, cfg: Any) -> None:
        """Range checks of the sampler keys this class reads (a SamplerConfig or a Hydra node)."""

    @classmethod
    def from_config(cls, cfg: Any, num_bins: int, device: Any = "cpu") -> "_BinSampler":
        """The sampler that ``cfg`` describes, over ``num_bins`` bins."""
        return cls(num_bins, device=device)

    def __init__(self, num_bins: int, device: Any = "cpu", method: str = "inverse_cdf"):
        if not (isinstance(num_bins, int) and not isinstance(num_bins, bool) and num_bins >= 1):
            raise SamplerConfigError(f"sampler num_bins must be an integer >= 1, got {num_bins!r}")
        if method not in _METHODS:
            raise SamplerConfigError(f"sampler method must be one of {', '.join(_METHODS)}, got {method!r}")
        self.num_bins = num_bins
        self.device = torch.device(device)
        self.method = method
        self._probs = torch.full((num_bins,), 1.0 / num_bins, dtype=_DTYPE, device=self.device)
        self._cdf = torch.empty_like(self._probs)
        self._refresh_cdf()

    # -- probabilities and sampling -----------------------------------------------------------

    # The cached tensors are written in place (out=), so they keep their storage (friendly to CUDA
    # graphs), and with few kernels: the update runs every control step and is launch-bound.
    def _refresh_cdf(self) -> None:
        cdf = torch.cumsum(self._probs, 0)
        # Rescale so the last entry is exactly 1 and every uniform in [0, 1) lands in a bin.
        torch.div(cdf, cdf[-1], out=self._cdf)

    def probabilities(self) -> torch.Tensor:
        """P over the bins (float64, sums to 1); a copy of the cached value."""
        return self._probs.clone()

    def sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Draw ``n`` bins i.i.d. from P (with replacement) as a LongTensor[n] on the sampler's device."""
        if self.method == "multinomial":
            if n == 0:
                return torch.empty(0, dtype=torch.long, device=self.device)
            return torch.multinomial(self._probs, n, replacement=True, generator=generator)
        u = torch.rand(n, generator=generator, dtype=_DTYPE, device=self.device)
        # right=True: bin i holds u in [cdf[i-1], cdf[i]), so zero-probability bins are never drawn.
        return torch.searchsorted(self._cdf, u, right=True).clamp_(max=self.num_bins - 1)

    # -- updates ------------------------------------------------------------------------------

    def update(self, bins: torch.Tensor, failed: torch.Tensor, visits: torch.Tensor | None = None) -> None:
        """Update from one batch of finished episodes.

        Args:
            bins: LongTensor[n], the bin each episode is charged to, values in [0, S).
            failed: BoolTensor[n], whether each episode failed.
            visits: optional Tensor[S] of per-bin visit counts; when given it replaces the count
                of episodes per bin (rate = failures per visit).

        This checks its input and so synchronises with the device; the environment's per-step
        path should accumulate counts and call :meth:`update_counts` instead.
        """
        bins = torch.as_tensor(bins, device=self.device)
        failed = torch.as_tensor(failed, device=self.device)
        if bins.ndim != 1 or failed.shape != bins.shape:
            raise SamplerConfigError(
                f"sampler update: bins and failed must be 1-D of equal length, got shapes "
                f"{tuple(bins.shape)} and {tuple(failed.shape)}"
            )
        if bins.dtype.is_floating_point or bins.dtype == torch.bool:
            raise SamplerConfigError(f"sampler update: bins must be an integer tensor, got {bins.dtype}")
        bins = bins.long()
        if bins.numel() and (int(bins.min()) < 0 or int(bins.max()) >= self.num_bins):
            raise SamplerConfigError(
                f"sampler update: bins must lie in [0, {self.num_bins}), got range "
                f"[{int(bins.min())}, {int(bins.max())}]"
            )
        failures = bin_counts(bins, self.num_bins, failed.to(torch.long))
        episodes = bin_counts(bins, self.num_bins) if visits is None else visits
        self.update_counts(episodes, failures)

    def update_counts(self, episodes: torch.Tensor, failures: torch.Tensor) -> None:
        """Update from per-bin counts of one batch: ``episodes[s]`` = n_s, ``failures[s]`` = f_s.

        Fixed shapes and no host synchronisation, so it can run every control step.
        """
        episodes = self._as_counts(episodes, "episodes")
        failures = self._as_counts(failures, "failures")
        self._update(episodes, failures)

    def _as_counts(self, x: torch.Tensor, name: str) -> torch.Tensor:
        x = torch.as_tensor(x, device=self.device)
        if x.shape != (self.num_bins,):
            raise SamplerConfigError(
                f"sampler update_counts: {name} must have shape ({self.num_bins},), got {tuple(x.shape)}"
            )
        return x.to(_DTYPE)

    def _update(self, episodes: torch.Tensor, failures: torch.Tensor) -> None:
        raise NotImplementedError

    def smoothed_failure(self) -> torch.Tensor:
        """The sampler's smoothed failure signal per bin (float64 [S]), for diagnostics."""
        raise NotImplementedError

    # -- state --------------------------------------------------------------------------------

    def hparams(self) -> dict[str, Any]:
        return {}

    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return {}

    def _recompute(self) -> None:
        pass

    def state_dict(self) -> dict[str, Any]:
        """Kind, number of bins, hyperparameters (for the record) and state tensors (copies)."""
        state = {k: v.detach().clone() for k, v in self._state_tensors().items()}
        return {"kind": self.kind, "num_bins": self.num_bins, "hparams": self.hparams(), "state": state}

    def load_state_dict(self, d: dict[str, Any]) -> None:
        """Restore the state saved by :meth:`state_dict`; hyperparameters stay those of this sampler."""
        if d.get("kind") != self.kind or d.get("num_bins") != self.num_bins:
            raise SamplerConfigError(
                f"sampler state is for a {d.get('kind')!r} sampler with {d.get('num_bins')} bins, "
                f"this is a {self.kind!r} sampler with {self.num_bins} bins"
            )
        own = self._state_tensors()
        saved = d.get("state", {})
        if set(saved) != set(own):
            raise SamplerConfigError(f"sampler state has keys {sorted(saved)}, expected {sorted(own)}")
        for key, tensor in own.items():
            tensor.copy_(torch.as_tensor(saved[key]).to(device=self.device, dtype=tensor.dtype))
        self._recompute()

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in self.hparams().items())
        return f"{type(self).__name__}(num_bins={self.num_bins}{', ' if args else ''}{args})"


class UniformSampler(_BinSampler):
    """P_s = 1/S; updates are accepted and ignored."""

    kind = "uniform"

    def _update(self, episodes: torch.Tensor, failures: torch.Tensor) -> None:
        pass

    def smoothed_failure(self) -> torch.Tensor:
        return torch.full((self.num_bins,), float("nan"), dtype=_DTYPE, device=self.device)


class _LookaheadSampler(_BinSampler):
    """A sampler whose weights are smoothed with the look-ahead kernel and whose state is an EMA."""

    def __init__(self, num_bins: int, gamma: float, K: int, empty_bins: str, device: Any, method: str):
        check_fraction("gamma", gamma)
        check_K(K)
        check_choice("empty_bins", empty_bins, EMPTY_BINS)
        super().__init__(num_bins, device=device, method=method)
        self.gamma = float(gamma)
        self.K = int(K)
        self.empty_bins = str(empty_bins)
        self._kernel = lookahead_kernel(self.gamma, self.K, device=self.device)
        self._index = lookahead_index(num_bins, self.K, device=self.device)

    @classmethod
    def check_config(cls, cfg: Any) -> None:
        check_fraction("gamma", cfg.gamma)
        check_K(cfg.K)
        check_choice("empty_bins", cfg.empty_bins, EMPTY_BINS)

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


class AdaptiveSampler(_LookaheadSampler):
    """The design: EMA of per-bin failure rates, look-ahead kernel, uniform mixture (see module doc).

    The defaults are the design's, and equal those of ``conf/sampler/adaptive.yaml`` and
    :class:`bmimic.sampling.config.SamplerConfig` (a test keeps the three equal).
    """

    kind = "adaptive"

    def __init__(
        self,
        num_bins: int,
        gamma: float = 0.9,
        lambda_uniform: float = 0.1,
        K: int = 5,
        alpha_smooth: float = 0.1,
        empty_bins: str = "decay",
        device: Any = "cpu",
        method: str = "inverse_cdf",
    ):
        check_fraction("lambda_uniform", lambda_uniform, closed_below=True)
        check_fraction("alpha_smooth", alpha_smooth)
        super().__init__(num_bins, gamma, K, empty_bins, device, method)
        self.lambda_uniform = float(lambda_uniform)
        self.alpha_smooth = float(alpha_smooth)
        self._rate = torch.zeros(num_bins, dtype=_DTYPE, device=self.device)

    @classmethod
    def check_config(cls, cfg: Any) -> None:
        super().check_config(cfg)
        check_fraction("lambda_uniform", cfg.lambda_uniform, closed_below=True)
        check_fraction("alpha_smooth", cfg.alpha_smooth)

    @classmethod
    def from_config(cls, cfg: Any, num_bins: int, device: Any = "cpu") -> "AdaptiveSampler":
        return cls(num_bins, gamma=cfg.gamma, lambda_uniform=cfg.lambda_uniform, K=cfg.K,
                   alpha_smooth=cfg.alpha_smooth, empty_bins=cfg.empty_bins, device=device)

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


class BeyondMimicSampler(_LookaheadSampler):
    """Released-code form: EMA of failure counts plus uniform_ratio/S, look-ahead kernel (see module doc).

    The defaults are the released code's (HybridRobotics/whole_body_tracking, ``MotionCommandCfg``).
    """

    kind = "beyondmimic"

    def __init__(
        self,
        num_bins: int,
        gamma: float = 0.8,
        K: int = 1,
        alpha: float = 0.001,
        uniform_ratio: float = 0.1,
        empty_bins: str = "decay",
        device: Any = "cpu",
        method: str = "inverse_cdf",
    ):
        check_fraction("alpha", alpha)
        check_uniform_ratio(uniform_ratio)
        super().__init__(num_bins, gamma, K, empty_bins, device, method)
        self.alpha = float(alpha)
        self.uniform_ratio = float(uniform_ratio)
        self._count = torch.zeros(num_bins, dtype=_DTYPE, device=self.device)
        self._recompute()

    @classmethod
    def check_config(cls, cfg: Any) -> None:
        super().check_config(cfg)
        check_fraction("alpha", cfg.alpha)
        check_uniform_ratio(cfg.uniform_ratio)

    @classmethod
    def from_config(cls, cfg: Any, num_bins: int, device: Any = "cpu") -> "BeyondMimicSampler":
        return cls(num_bins, gamma=cfg.gamma, K=cfg.K, alpha=cfg.alpha, uniform_ratio=cfg.uniform_ratio,
                   empty_bins=cfg.empty_bins, device=device)

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
