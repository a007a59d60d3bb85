"""`BinSampler`: what every sampler shares (cached probabilities and their CDF, inverse-CDF draws,
`update`/`update_counts`, the state dict), and `bin_counts`, the fixed-shape histogram the samplers
and the sampler's feedback count with. A sampler subclasses BinSampler and implements what it learns
from (its `signals`: `_update` for episode outcomes, `update_errors`, ...; see
:mod:`bmimic.sampling.samplers` for the built-in ones and how to add one)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Generic, TypeVar, cast

from bmimic.cli.deferred import import_on_first_use
from bmimic.sampling.checks import SamplerConfigError

if TYPE_CHECKING:
    import torch

    from bmimic.sampling.schemas import SamplerConfig
else:
    torch = import_on_first_use("torch", globals())  # a sampler's module imports this one before any config exists

ERROR_COMPONENTS = ("body_pos_m", "body_ori_rad", "body_lin_vel_m_per_s", "max_body_pos_m")
"""The per-env tracking errors the sampler's feedback sums per bin for samplers that declare
``TRACKING_ERRORS``: the mean over tracked bodies of the position (anchor-relative reference),
orientation and linear-velocity errors, and the largest body position error."""
# Probabilities and state are torch.float64, so 10^6 updates at alpha=0.001 accumulate no visible rounding
# (written out where used: a module-level torch value would import torch with the config checks, which
# read the sampler classes' checks, bmimic.sampling.config).
METHODS = ("inverse_cdf", "multinomial")
ConfigT = TypeVar("ConfigT", bound="SamplerConfig")


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


class BinSampler(Generic[ConfigT]):
    """Shared plumbing: cached probabilities and CDF, sampling, update(), state dict. `kind` is the
    name it is registered under and `schema` its config dataclass
    (`bmimic.sampling.registry.register_sampler` sets both)."""

    kind = ""
    schema: type[SamplerConfig] | None = None
    signals: tuple = ()
    """What the sampler learns from (:class:`bmimic.sampling.signals.Signal` s): the sampler's
    feedback measures each and delivers it, at its cadence, to the method the signal names
    (:meth:`update_counts`, :meth:`update_errors`, :meth:`observe_eval`). None: it never changes."""

    cfg: ConfigT
    """The validated config the sampler was built with."""

    def __init__(self, num_bins: int, cfg: ConfigT | None = None, device: torch.device | str = "cpu",
                 method: str = "inverse_cdf"):
        """`cfg`: the sampler's validated config (an instance of its `schema`, checked by
        `bmimic.sampling.config.validate_sampler_config`); None: the schema's defaults."""
        if not (isinstance(num_bins, int) and not isinstance(num_bins, bool) and num_bins >= 1):
            raise SamplerConfigError(f"sampler num_bins must be an integer >= 1, got {num_bins!r}")
        if method not in METHODS:
            raise SamplerConfigError(f"sampler method must be one of {', '.join(METHODS)}, got {method!r}")
        self.cfg = cast(ConfigT, cfg if cfg is not None or self.schema is None else self.schema())
        self.num_bins = num_bins
        self.device = torch.device(device)
        self.method = method
        self._probs = torch.full((num_bins,), 1.0 / num_bins, dtype=torch.float64, device=self.device)
        self._cdf = torch.empty_like(self._probs)
        self._num_clips = 1
        self._balance_clip: torch.Tensor | None = None  # clip of each bin, when clip_balance is "clips"
        self._refresh_cdf()

    def set_clips(self, bin_clip: torch.Tensor, bin_last_in_clip: torch.Tensor, num_clips: int,
                  clip_balance: str = "bins", clip_weights: Any = None) -> None:
        """Make the sampler aware of a library's clips (``bin_clip``: the clip of each bin;
        ``bin_last_in_clip``: the last bin of each bin's clip).

        ``clip_balance="clips"`` gives clip c the total probability w_c / sum(w) (``clip_weights``,
        default all 1, so 1/C each) and keeps the sampler's own proportions within the clip:
        P'_s = P_s / M_c * w_c / sum(w), with M_c the mass of clip c under P (a clip of zero mass is
        uniform within itself). "bins" leaves P over all bins as the sampler computes it.
        """
        bin_clip = torch.as_tensor(bin_clip, device=self.device).long()
        if bin_clip.shape != (self.num_bins,):
            raise SamplerConfigError(f"sampler set_clips: bin_clip must have shape ({self.num_bins},)")
        self._num_clips = int(num_clips)
        if clip_balance == "clips" and self._num_clips > 1:
            w = torch.ones(self._num_clips, dtype=torch.float64) if clip_weights is None else torch.as_tensor(
                clip_weights, dtype=torch.float64)
            if w.shape != (self._num_clips,) or not bool((w > 0).all()) or not bool(torch.isfinite(w).all()):
                raise SamplerConfigError(f"clip weights must be {self._num_clips} finite numbers > 0, got "
                                         f"{w.tolist()}")
            w = (w / w.sum()).to(self.device)
            size = torch.zeros(self._num_clips, dtype=torch.float64, device=self.device).index_add_(
                0, bin_clip, torch.ones(self.num_bins, dtype=torch.float64, device=self.device))
            self._balance_clip = bin_clip
            self._bin_clip_size = size[bin_clip]
            self._bin_clip_share = w[bin_clip]
        self._recompute()
        self._refresh_cdf()

    # -- probabilities and sampling -----------------------------------------------------------

    # The cached tensors are written in place (out=), so they keep their storage (friendly to CUDA
    # graphs), and with few kernels: the update runs every control step and is launch-bound.
    def _refresh_cdf(self) -> None:
        if self._balance_clip is not None:
            c = self._balance_clip
            mass = torch.zeros(self._num_clips, dtype=torch.float64, device=self.device).index_add_(0, c, self._probs)[c]
            within = torch.where(mass > 0, self._probs / mass, 1.0 / self._bin_clip_size)
            torch.mul(within, self._bin_clip_share, out=self._probs)
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
        u = torch.rand(n, generator=generator, dtype=torch.float64, device=self.device)
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
        return x.to(torch.float64)

    def _update(self, episodes: torch.Tensor, failures: torch.Tensor) -> None:
        """Learn from one batch's per-bin counts (the signal ``EPISODE_OUTCOMES``, which a sampler that
        implements this declares). By default nothing: the uniform sampler, and samplers that learn from
        other signals, accept the counts and ignore them."""

    def update_errors(self, error_sums: torch.Tensor, steps: torch.Tensor) -> None:
        """One iteration's tracking errors per bin (signal ``TRACKING_ERRORS``): ``error_sums``
        [len(ERROR_COMPONENTS), S] sums over the env-steps spent at a frame of each bin, ``steps`` [S]
        their number. Fixed shapes, no host synchronisation."""

    def observe_eval(self, clip_failed: torch.Tensor, iterations: int) -> None:
        """The outcome of one evaluation (signal ``CLIP_OUTCOMES``): ``clip_failed`` [C] whether
        an evaluation episode of each clip failed; ``iterations`` since the previous evaluation."""

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


__all__ = ["ERROR_COMPONENTS", "METHODS", "BinSampler", "bin_counts"]
