"""The evaluation-driven samplers' signal (phc, protomotions): one rollout per clip from its first frame.

PHC (``im_amp.py`` eval with ``motion_times = 0``) and ProtoMotions v3 (``MimicEvaluator``:
``motion_times[env_ids] = 0``, up to ``max_eval_steps``) evaluate each motion once, from its start,
and call it failed when that rollout failed before the motion's end (PHC: the whole motion; ProtoMotions:
its first ``max_eval_steps`` steps). bmimic does the same in its evaluation environment: per clip,
one episode starts at the clip's first frame and runs the deterministic policy to the clip's last
frame, or for ``max_s`` seconds when that is shorter, under the evaluation's failure rule
(:class:`bmimic.training.evaluator.Evaluator`: a termination, a broken world, or the optional
``eval.max_mpkpe_rel_mm``). A clip failed when its rollout failed.

The rollouts of all clips run side by side in one wave of the evaluation environment; the wave lasts
as long as the longest clip (or ``max_s``), so on long clips this is a long, sequential evaluation.
``clip_start_rollouts`` runs R such rollouts per clip; the whole-clip evaluation
(bmimic.training.whole_clip) is built on it, with R rollouts per clip under perturbations and no ``max_s``.
"""

from __future__ import annotations

import contextlib
import copy

import numpy as np
import pandas as pd
import torch

from bmimic.runs.schema import CLIP_ROLLOUT_COLUMNS


def clip_bounds(layout) -> tuple[np.ndarray, np.ndarray]:
    """Each clip's first frame and exclusive end frame (a single motion: one clip, all frames)."""
    starts = layout.clip_starts.cpu().numpy() if hasattr(layout, "clip_starts") else np.zeros(1, dtype=np.int64)
    return starts.astype(np.int64), np.r_[starts[1:], layout.num_frames].astype(np.int64)


def clip_start_rollouts(evaluator, policy, per_clip: int = 1, max_s: float | None = None):
    """``per_clip`` rollouts per clip of ``evaluator``'s layout, each from the clip's first frame to its
    last frame (or for ``max_s`` seconds when that is shorter), in ``evaluator``'s environment under its
    failure rule: its Rollouts (bmimic.training.evaluator), the episodes clip by clip with the columns
    ``clip`` and ``rollout`` (0..per_clip-1) first. Episodes beyond the environment's size run in later waves."""
    layout = evaluator.layout
    starts, ends = clip_bounds(layout)
    steps = max(1, int((ends - starts).max()) - 1)  # steps from a clip's first frame to its last
    if max_s is not None:
        steps = min(steps, max(1, int(round(max_s / evaluator.env.step_dt))))
    one = copy.copy(evaluator)  # same environment and failure rule, other starts and horizon
    one.frames = np.repeat(starts, per_clip)
    one.bins = layout.frame_to_bin.cpu().numpy()[one.frames]
    one.horizon_steps = steps
    out = one.run_episodes(policy)
    out.episodes.insert(0, "rollout", np.tile(np.arange(per_clip), len(starts)))
    out.episodes.insert(0, "clip", np.repeat(np.arange(len(starts)), per_clip))
    return out


def clip_rollouts(evaluator, policy, max_s: float | None = None) -> pd.DataFrame:
    """One rollout per clip of ``evaluator``'s layout (module docstring): CLIP_ROLLOUT_COLUMNS, one row
    per clip in clip order."""
    layout = evaluator.layout
    starts, ends = clip_bounds(layout)
    ep = clip_start_rollouts(evaluator, policy, 1, max_s).episodes
    names = list(getattr(layout, "clip_names", ("motion",)))
    broken = ep["broken"].to_numpy(dtype=bool) if "broken" in ep else np.zeros(len(ep), dtype=bool)
    failed = ep["failed"].to_numpy(dtype=bool)
    return pd.DataFrame({
        "clip": np.arange(len(starts)), "clip_name": names[: len(starts)],
        "start_frame": ep["start_frame"].to_numpy(), "end_frame": ep["end_frame"].to_numpy(),
        "steps": ep["steps"].to_numpy(), "failed": failed, "terminated": ep["terminated"].to_numpy(dtype=bool),
        "broken": broken, "reached_end": ~failed & (ep["end_frame"].to_numpy() == ends - 1),
    }, columns=list(CLIP_ROLLOUT_COLUMNS))


def clips_failed(rollouts: pd.DataFrame, num_clips: int) -> torch.Tensor:
    """BoolTensor [num_clips]: whether each clip's rollout failed (clip_rollouts' rows)."""
    out = torch.zeros(num_clips, dtype=torch.bool)
    out[torch.tensor(rollouts["clip"].to_numpy(dtype=np.int64))] = torch.tensor(rollouts["failed"].to_numpy(dtype=bool))
    return out


@contextlib.contextmanager
def eval_mode(policy):
    """The policy in eval mode for the block, back in the mode it was in after it."""
    was_training = policy.training
    policy.eval()
    try:
        yield policy
    finally:
        if was_training:
            policy.train()


__all__ = ["CLIP_ROLLOUT_COLUMNS", "clip_bounds", "clip_rollouts", "clip_start_rollouts", "clips_failed", "eval_mode"]
