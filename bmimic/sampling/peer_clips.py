r"""The field's evaluation-driven clip samplers (issue 24), and the base of every sampler whose weights
live on clips or sub-clips. Each YAML in ``conf/sampler/`` cites its source and marks what the source
leaves open and how bmimic chose it; the formulas are here (EGM and GMT: :mod:`bmimic.sampling.peer_errors`).

Both learn from one rollout per clip from the clip's first frame after each periodic evaluation
(:mod:`bmimic.training.clip_rollouts`: the clip failed when that rollout failed before the clip's end,
or before ``rollout_max_s`` seconds when set), as the sources evaluate each motion from its start.

**PHCSampler** (``phc``; PHC's ``auto_pmcp_soft``, ZhengyiLuo/PHC ``phc/learning/im_amp.py`` and
``phc/utils/motion_lib_base.py``). After each evaluation, :math:`h_m \mathrel{+}= 1` for every clip m
whose rollout failed, and :math:`p_m = h_m / \sum h`; when no clip failed that evaluation, p is
uniform over clips (``update_soft_sampling_weight`` resets to uniform; h is kept for the next
failure); ``mode: hard`` (``auto_pmcp``) is uniform over the clips that failed the latest evaluation
instead (uniform over all when none did).

**ProtoMotionsSampler** (``protomotions``; ProtoMotions v3, ``mimic_evaluator._update_motion_sampling_weights``).
Weights :math:`w_m` start at 1; after each evaluation, K iterations after the previous one,
:math:`w_m \leftarrow w_m d_s^K` if clip m succeeded, :math:`w_m \leftarrow 1` if it failed (``failure_decay``
0, as every shipped experiment) or :math:`w_m / d_f^K` otherwise, then :math:`w \leftarrow \max(w, w_{min})`
with :math:`w_{min} = 1/C` by default; :math:`p_m = w_m / \sum w`.

PHC and ProtoMotions choose motions, not times: a clip's probability is spread evenly over its bins
(bmimic's uniform start within a clip), so on a single motion both are the uniform sampler. Their
per-clip (GMT: per-sub-clip) state is kept in tensors of length S whose first C (G) entries are
used, so every state tensor has a fixed shape whatever the motion library.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional, TypeVar

from bmimic.cli.deferred import import_on_first_use
from bmimic.sampling.base import BinSampler
from bmimic.sampling.checks import SamplerConfigError, check_choice, check_fraction, check_positive, fail
from bmimic.sampling.registry import register_sampler
from bmimic.sampling.schemas import SamplerConfig
from bmimic.sampling.signals import CLIP_OUTCOMES

if TYPE_CHECKING:
    import torch
else:
    torch = import_on_first_use("torch", globals())  # composing a config imports this module, not torch

PHC_MODES = ("soft", "hard")
"""`mode` of the PHC sampler."""


@dataclass
class ClipWeightingConfig(SamplerConfig):
    """Base of the schemas of samplers that weight clips (or sub-clips) themselves: gmt, phc, protomotions."""

    def check(self) -> None:
        if self.clip_balance != "bins":
            fail("clip_balance", f"bins (the {self.kind} sampler weights clips itself)", self.clip_balance)


def _optional_float(x: Optional[float]) -> Optional[float]:
    return None if x is None else float(x)


GroupConfigT = TypeVar("GroupConfigT", bound=ClipWeightingConfig)


class GroupSampler(BinSampler[GroupConfigT]):
    """A sampler whose weights live on groups of consecutive bins (clips or sub-clips); each group's
    share is spread evenly over its bins."""

    def __init__(self, num_bins: int, cfg: GroupConfigT | None = None, device: torch.device | str = "cpu"):
        super().__init__(num_bins, cfg, device=device)
        self._set_groups(torch.zeros(num_bins, dtype=torch.long))

    def _groups_of(self, bin_clip: torch.Tensor) -> torch.Tensor:
        """The group of each bin: its clip (a subclass may cut clips finer)."""
        return bin_clip

    def _set_groups(self, bin_clip: torch.Tensor) -> None:
        group = self._groups_of(bin_clip.cpu().long())
        self.num_groups = int(group.max()) + 1
        size = torch.bincount(group, minlength=self.num_groups).to(torch.float64)
        self._group = group.to(self.device)
        self._bin_group_size = size.to(self.device)[self._group]

    def set_clips(self, bin_clip: torch.Tensor, bin_last_in_clip: torch.Tensor, num_clips: int,
                  clip_balance: str = "bins", clip_weights: Any = None) -> None:
        if clip_balance != "bins":
            raise SamplerConfigError(f"sampler.clip_balance: the {self.kind} sampler weights clips itself; "
                                     "use clip_balance=bins")
        self._set_groups(torch.as_tensor(bin_clip))
        super().set_clips(bin_clip, bin_last_in_clip, num_clips)

    def group_sums(self, per_bin: torch.Tensor) -> torch.Tensor:
        """Sum of a per-bin quantity over each group, in a tensor of length S (first num_groups used)."""
        return torch.zeros(self.num_bins, dtype=per_bin.dtype, device=self.device).index_add_(0, self._group, per_bin)

    def _spread(self, weights: torch.Tensor) -> None:
        """P from per-group weights (length S, first num_groups used): each group's share spread
        evenly over its bins; uniform while every weight is 0."""
        share = weights[self._group] / self._bin_group_size
        total = share.sum()
        self._probs.copy_(torch.where(total > 0, share / total, 1.0 / self.num_bins))
        self._refresh_cdf()


# ------------------------------------------------------------------------------------------------ PHC

@dataclass
class PHCConfig(ClipWeightingConfig):
    """`sampler=phc`: PHC's evaluation-driven hard-negative mining over clips."""

    name: str = "phc"
    kind: str = "phc"
    mode: str = "soft"
    """"soft" (auto_pmcp_soft, PHC's default): p_m = h_m / sum(h), h the failed evaluations of clip m,
    uniform when the latest evaluation failed no clip; "hard" (auto_pmcp): uniform over the clips that
    failed the latest evaluation."""
    rollout_max_s: Optional[float] = None
    """Seconds of each clip's evaluation rollout from its first frame, > 0; null: to the clip's end
    (PHC evaluates the whole motion)."""

    def check(self) -> None:
        super().check()
        check_choice("mode", self.mode, PHC_MODES)
        if self.rollout_max_s is not None:
            check_positive("rollout_max_s", self.rollout_max_s)


@register_sampler("phc", PHCConfig)
class PHCSampler(GroupSampler[PHCConfig]):
    """Clip weights from evaluation failures (module doc)."""

    signals = (CLIP_OUTCOMES,)

    def __init__(self, num_bins: int, cfg: PHCConfig | None = None, device: torch.device | str = "cpu"):
        super().__init__(num_bins, cfg, device=device)
        self.mode = self.cfg.mode
        self.rollout_max_s = _optional_float(self.cfg.rollout_max_s)
        self._failures = torch.zeros(num_bins, dtype=torch.float64, device=self.device)
        self._last_failed = torch.zeros(num_bins, dtype=torch.float64, device=self.device)

    def observe_eval(self, clip_failed: torch.Tensor, iterations: int) -> None:
        failed = torch.zeros(self.num_bins, dtype=torch.float64, device=self.device)
        failed[: len(clip_failed)] = torch.as_tensor(clip_failed, device=self.device).to(torch.float64)
        self._failures += failed
        self._last_failed.copy_(failed)
        self._recompute()

    def _recompute(self) -> None:
        w = self._failures if self.mode == "soft" else self._last_failed
        # The latest evaluation failed no clip (or none ran yet): every clip alike, PHC's reset to
        # uniform in both modes; soft keeps h for the next evaluation that fails one.
        self._spread(torch.where(self._last_failed.sum() > 0, w, torch.ones_like(w)))

    def smoothed_failure(self) -> torch.Tensor:
        """Each bin's clip failure count h (soft) or latest outcome (hard)."""
        return (self._failures if self.mode == "soft" else self._last_failed)[self._group].clone()

    def hparams(self) -> dict[str, Any]:
        return {"mode": self.mode, "rollout_max_s": self.rollout_max_s}

    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return {"failures": self._failures, "last_failed": self._last_failed}


# ---------------------------------------------------------------------------------------- ProtoMotions
@dataclass
class ProtoMotionsConfig(ClipWeightingConfig):
    """`sampler=protomotions`: ProtoMotions v3's evaluation-driven multiplicative clip weights."""

    name: str = "protomotions"
    kind: str = "protomotions"
    success_decay: float = 0.999
    """d_s: a clip that succeeded an evaluation is multiplied by d_s^K (K iterations since the last), in (0, 1]."""
    failure_decay: float = 0.0
    """d_f: a failed clip is divided by d_f^K; 0 resets it to 1 (every shipped experiment), in [0, 1]."""
    min_weight: Optional[float] = None
    """Floor of every weight, > 0; null: 1 / number of clips (ProtoMotions' default)."""
    rollout_max_s: Optional[float] = 12.0
    """Seconds of each clip's evaluation rollout from its first frame, > 0 (ProtoMotions' max_eval_steps,
    600 steps at its 50 Hz G1 control rate); null: to the clip's end."""

    def check(self) -> None:
        super().check()
        check_fraction("success_decay", self.success_decay)
        check_fraction("failure_decay", self.failure_decay, closed_below=True)
        if self.min_weight is not None:
            check_positive("min_weight", self.min_weight)
        if self.rollout_max_s is not None:
            check_positive("rollout_max_s", self.rollout_max_s)


@register_sampler("protomotions", ProtoMotionsConfig)
class ProtoMotionsSampler(GroupSampler[ProtoMotionsConfig]):
    """Multiplicative clip weights from evaluations with a floor (module doc)."""

    signals = (CLIP_OUTCOMES,)

    def __init__(self, num_bins: int, cfg: ProtoMotionsConfig | None = None, device: torch.device | str = "cpu"):
        super().__init__(num_bins, cfg, device=device)
        self.success_decay, self.failure_decay = float(self.cfg.success_decay), float(self.cfg.failure_decay)
        self.min_weight = _optional_float(self.cfg.min_weight)
        self.rollout_max_s = _optional_float(self.cfg.rollout_max_s)
        self._weight = torch.ones(num_bins, dtype=torch.float64, device=self.device)

    def floor(self) -> float:
        """The weight floor in force (min_weight, or 1 / number of clips)."""
        return self.min_weight if self.min_weight is not None else 1.0 / self.num_groups

    def observe_eval(self, clip_failed: torch.Tensor, iterations: int) -> None:
        c = len(clip_failed)
        failed = torch.as_tensor(clip_failed, device=self.device).bool()
        w = self._weight[:c]
        k = max(int(iterations), 1)
        on_failure = torch.ones_like(w) if self.failure_decay == 0 else w / self.failure_decay**k
        w.copy_(torch.where(failed, on_failure, w * self.success_decay**k).clamp(min=self.floor()))
        self._recompute()

    def _recompute(self) -> None:
        self._spread(self._weight)

    def smoothed_failure(self) -> torch.Tensor:
        """Each bin's clip weight w (not a failure rate)."""
        return self._weight[self._group].clone()

    def hparams(self) -> dict[str, Any]:
        return {"success_decay": self.success_decay, "failure_decay": self.failure_decay,
                "min_weight": self.min_weight, "rollout_max_s": self.rollout_max_s}

    def _state_tensors(self) -> dict[str, torch.Tensor]:
        return {"weight": self._weight}


__all__ = ["PHC_MODES", "ClipWeightingConfig", "GroupSampler", "PHCConfig", "PHCSampler", "ProtoMotionsConfig", "ProtoMotionsSampler"]
