r"""The field's tracking-error samplers (issue 24): EGM and GMT, on bmimic's bins, MDP and simulator.
Each YAML in ``conf/sampler/`` cites its source and marks what the source leaves open and how bmimic
chose it; the formulas are here (PHC and ProtoMotions: :mod:`bmimic.sampling.peer_clips`). The episode
sampler's feedback measures the errors in the step (:meth:`SamplerFeedback.measure`).

**EGMSampler** (``egm``; EGM, arXiv 2512.19043, "bin-based cross-motion curriculum adaptive sampling").
Per bin, an EMA of a composite tracking error: with :math:`\bar e_b` the iteration's mean over
env-steps at a frame of bin b of :math:`w_{pos} e_{pos} + w_{ori} e_{ori} + w_{vel} e_{vel}`,

.. math::
    e_b \leftarrow (1-\beta)\, e_b + \beta\, \bar e_b \ \ (\text{the first visit sets } e_b = \bar e_b;
    \text{ unvisited bins hold}),\qquad \hat e = e / \textstyle\sum_j e_j,\qquad
    P_b = (1-u)\, \hat e_b^{\,\tau} / \textstyle\sum_j \hat e_j^{\,\tau} + u / S,

uniform while no error was seen. The exponent :math:`\tau` and the uniform ratio u move linearly from
their start to their end values over ``schedule_iterations`` iterations (then stay).

**GMTSampler** (``gmt``; GMT, arXiv 2506.14770 section 3.1). Clips are cut into sub-clips of at most
``subclip_bins`` bins. Each sub-clip i has a completion level :math:`c_i` (initially 10); every
episode that started in it and finished without failing multiplies it by 0.99, floored at 1:
:math:`c_i \leftarrow \max(c_i\, 0.99^{n_i - f_i}, 1)`. With :math:`E_i` the latest iteration's mean,
over the env-steps in the sub-clip, of the largest body position error,

.. math:: s_i = c_i \ (c_i > 1),\qquad s_i = \min(E_i / 0.15\,\mathrm{m},\, 1)^5 \ (c_i = 1),\qquad
    P_b = s_{i(b)} / (\textstyle\sum_j s_j\ |i(b)|),

spread evenly over the sub-clip's |i| bins (uniform while every s is 0).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional

from bmimic.cli.deferred import import_on_first_use
from bmimic.runs.schema import ITERATION
from bmimic.sampling.base import BinSampler
from bmimic.sampling.checks import check_fraction, check_int_at_least, check_nonnegative, check_positive, fail
from bmimic.sampling.peer_clips import ClipWeightingConfig, GroupSampler
from bmimic.sampling.registry import register_sampler
from bmimic.sampling.schemas import SamplerConfig
from bmimic.sampling.signals import EPISODE_OUTCOMES, TRACKING_ERRORS

if TYPE_CHECKING:
    import torch
else:
    torch = import_on_first_use("torch", globals())  # composing a config imports this module, not torch

UNSET_SCHEDULE_ITERATIONS = 1000
"""EGM's schedule length where no run's max_iterations fills a null ``schedule_iterations``."""


# ------------------------------------------------------------------------------------------------ EGM
@dataclass
class EGMConfig(SamplerConfig):
    """`sampler=egm`: EGM's bin-based adaptive sampling from an EMA of a composite tracking error."""

    name: str = "egm"
    kind: str = "egm"
    ema: float = 0.1
    """EMA weight beta of an iteration's mean error in a bin, in (0, 1]."""
    weight_body_pos: float = 1.0
    """Weight of the mean body position error (m) in the composite error, >= 0."""
    weight_body_ori: float = 0.1
    """Weight of the mean body orientation error (rad), >= 0."""
    weight_body_lin_vel: float = 0.1
    """Weight of the mean body linear-velocity error (m/s), >= 0."""
    power_start: float = 0.5
    """Exponent tau of the normalised error at iteration 0 (the paper's "smoothing temperature";
    low = flat), > 0."""
    power_end: float = 2.0
    """Exponent tau after schedule_iterations (high = sharp), > 0."""
    uniform_start: float = 0.5
    """Uniform ratio u at iteration 0, in [0, 1]."""
    uniform_end: float = 0.1
    """Uniform ratio u after schedule_iterations, in [0, 1]."""
    schedule_iterations: Optional[int] = None
    """Iterations over which tau and u move linearly from start to end (>= 1); null: the run's
    max_iterations (the paper's schedule spans training; filled by bmimic.config.resolve_runtime),
    or peer_errors.UNSET_SCHEDULE_ITERATIONS where no run exists (benchmarks, unit tests)."""

    def check(self) -> None:
        check_fraction("ema", self.ema)
        for key in ("weight_body_pos", "weight_body_ori", "weight_body_lin_vel"):
            check_nonnegative(key, getattr(self, key))
        if self.weight_body_pos + self.weight_body_ori + self.weight_body_lin_vel <= 0:
            fail("weight_body_pos", "weights whose sum is > 0", self.weight_body_pos)
        for key in ("power_start", "power_end"):
            check_positive(key, getattr(self, key))
        for key in ("uniform_start", "uniform_end"):
            check_fraction(key, getattr(self, key), closed_below=True)
        if self.schedule_iterations is not None:
            check_int_at_least("schedule_iterations", self.schedule_iterations, 1)


@register_sampler("egm", EGMConfig)
class EGMSampler(BinSampler[EGMConfig]):
    """EMA of a composite tracking error per bin, normalised, raised to a scheduled power, mixed with
    a scheduled uniform ratio (module doc)."""

    signals = (TRACKING_ERRORS,)

    def __init__(self, num_bins: int, cfg: EGMConfig | None = None, device: torch.device | str = "cpu"):
        super().__init__(num_bins, cfg, device=device)
        cfg = self.cfg
        self.ema = float(cfg.ema)
        self.weights = (float(cfg.weight_body_pos), float(cfg.weight_body_ori), float(cfg.weight_body_lin_vel))
        self.power = (float(cfg.power_start), float(cfg.power_end))
        self.uniform = (float(cfg.uniform_start), float(cfg.uniform_end))
        self.schedule_iterations = int(UNSET_SCHEDULE_ITERATIONS if cfg.schedule_iterations is None
                                       else cfg.schedule_iterations)
        self._w = torch.tensor(self.weights, dtype=torch.float64, device=self.device)
        self._error = torch.zeros(num_bins, dtype=torch.float64, device=self.device)
        self._seen = torch.zeros(num_bins, dtype=torch.float64, device=self.device)
        self._iteration = torch.zeros((), dtype=torch.float64, device=self.device)

    def update_errors(self, error_sums: torch.Tensor, steps: torch.Tensor) -> None:
        mean = (self._w @ error_sums[:3].to(torch.float64)) / steps.clamp(min=1.0)
        visited = steps > 0
        target = torch.where(self._seen > 0, self._error.lerp(mean, self.ema), mean)
        self._error.copy_(torch.where(visited, target, self._error))
        self._seen.copy_(torch.where(visited, 1.0, self._seen))
        self._iteration += 1
        self._recompute()

    def schedule(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(tau, u) now (0-d tensors on the sampler's device)."""
        frac = (self._iteration / self.schedule_iterations).clamp(max=1.0)
        return (self.power[0] + (self.power[1] - self.power[0]) * frac,
                self.uniform[0] + (self.uniform[1] - self.uniform[0]) * frac)

    def _recompute(self) -> None:
        tau, u = self.schedule()
        total = self._error.sum()
        q = (self._error / total.clamp(min=1e-300)).pow(tau)
        q_total = q.sum()
        p = torch.where((total > 0) & (q_total > 0), q / q_total, 1.0 / self.num_bins)
        torch.add(p * (1.0 - u), u / self.num_bins, out=self._probs)
        self._refresh_cdf()

    def smoothed_failure(self) -> torch.Tensor:
        """The EMA of the composite tracking error e (not a failure rate)."""
        return self._error.clone()

    def hparams(self) -> dict[str, Any]:
        return {"ema": self.ema, "weights": list(self.weights), "power": list(self.power),
                "uniform": list(self.uniform), "schedule_iterations": self.schedule_iterations}

    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return {"error": self._error, "seen": self._seen, ITERATION: self._iteration}


# ------------------------------------------------------------------------------------------------ GMT
@dataclass
class GMTConfig(ClipWeightingConfig):
    """`sampler=gmt`: GMT's completion-level sampling of sub-clips."""

    name: str = "gmt"
    kind: str = "gmt"
    subclip_bins: int = 10
    """Longest sub-clip, in bins (10 = GMT's 10 s at 1 s bins); clips are cut from their start."""
    initial_level: float = 10.0
    """Completion level c of a sub-clip never completed, >= min_level."""
    completion_decay: float = 0.99
    """c is multiplied by this at each completion, in (0, 1]."""
    min_level: float = 1.0
    """Floor of c (a sub-clip at the floor is sampled by its error), > 0."""
    error_scale_m: float = 0.15
    """At the floor, s = min(E / error_scale_m, 1) ^ error_power, E in m; > 0."""
    error_power: float = 5.0
    """See error_scale_m; > 0."""

    def check(self) -> None:
        super().check()
        check_int_at_least("subclip_bins", self.subclip_bins, 1)
        check_fraction("completion_decay", self.completion_decay)
        for key in ("min_level", "error_scale_m", "error_power"):
            check_positive(key, getattr(self, key))
        check_positive("initial_level", self.initial_level)
        if self.initial_level < self.min_level:
            fail("initial_level", f"a number >= min_level ({self.min_level})", self.initial_level)


@register_sampler("gmt", GMTConfig)
class GMTSampler(GroupSampler[GMTConfig]):
    """Completion levels per sub-clip, then the largest body error once mastered (module doc)."""

    signals = (EPISODE_OUTCOMES, TRACKING_ERRORS)

    def __init__(self, num_bins: int, cfg: GMTConfig | None = None, device: torch.device | str = "cpu"):
        super().__init__(num_bins, cfg, device=device)
        cfg = self.cfg
        self.subclip_bins = int(cfg.subclip_bins)
        self.initial_level, self.completion_decay = float(cfg.initial_level), float(cfg.completion_decay)
        self.min_level, self.error_scale_m, self.error_power = float(cfg.min_level), float(cfg.error_scale_m), \
            float(cfg.error_power)
        self._level = torch.full((num_bins,), self.initial_level, dtype=torch.float64, device=self.device)
        self._max_error = torch.zeros(num_bins, dtype=torch.float64, device=self.device)
        self._recompute()

    def _groups_of(self, bin_clip: torch.Tensor) -> torch.Tensor:
        """Sub-clips: each clip's bins cut from its first bin into runs of subclip_bins."""
        idx = torch.arange(len(bin_clip))
        first = torch.zeros(int(bin_clip.max()) + 1, dtype=torch.long).scatter_reduce(
            0, bin_clip, idx, "amin", include_self=False)
        sub = (idx - first[bin_clip]) // int(self.cfg.subclip_bins)
        new_group = torch.ones_like(idx, dtype=torch.bool)
        new_group[1:] = (bin_clip[1:] != bin_clip[:-1]) | (sub[1:] != sub[:-1])
        return new_group.long().cumsum(0) - 1

    def _update(self, episodes: torch.Tensor, failures: torch.Tensor) -> None:
        completions = self.group_sums((episodes - failures).clamp(min=0.0))
        self._level.mul_(torch.pow(self.completion_decay, completions)).clamp_(min=self.min_level)
        self._recompute()

    def update_errors(self, error_sums: torch.Tensor, steps: torch.Tensor) -> None:
        steps_g = self.group_sums(steps.to(torch.float64))
        mean = self.group_sums(error_sums[3].to(torch.float64)) / steps_g.clamp(min=1.0)
        self._max_error.copy_(torch.where(steps_g > 0, mean, self._max_error))
        self._recompute()

    def _recompute(self) -> None:
        at_floor = (self._max_error / self.error_scale_m).clamp(max=1.0).pow(self.error_power)
        self._spread(torch.where(self._level > self.min_level, self._level, at_floor))

    def smoothed_failure(self) -> torch.Tensor:
        """Each bin's sub-clip completion level c (not a failure rate)."""
        return self._level[self._group].clone()

    def hparams(self) -> dict[str, Any]:
        return {"subclip_bins": self.subclip_bins, "initial_level": self.initial_level,
                "completion_decay": self.completion_decay, "min_level": self.min_level,
                "error_scale_m": self.error_scale_m, "error_power": self.error_power}

    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return {"level": self._level, "max_error": self._max_error}


__all__ = ["EGMConfig", "EGMSampler", "GMTConfig", "GMTSampler"]
