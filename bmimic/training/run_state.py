"""What a training checkpoint holds and how a trainer is restored from one: the counters (`Progress`),
the meta a checkpoint must match, the state written (networks, optimiser, sampler, RNG, config) and the
restore that checks it, loads it and reads the run's tables back (`RunRecord.truncate`). The Trainer
(bmimic.training.runner, the `trainer` argument) hands its checkpoint methods to these functions."""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bmimic import BmimicError
from bmimic.runs.folder import checkpoint_path, checkpoints_dir, latest_checkpoint
from bmimic.runtime import rng_state, set_rng_state
from bmimic.training.checkpoints import (
    CHECKPOINT_FORMAT,
    CheckpointMismatchError,
    atomic_torch_save,
    mismatch_detail,
    motion_meta,
)
from bmimic.training.resume import key_allowed

log = logging.getLogger(__name__)


@dataclass
class Progress:
    """Counters a checkpoint carries so a resumed run continues them."""

    iteration: int = 0
    env_steps: int = 0
    wall_time_s: float = 0.0
    last_eval: dict = field(default_factory=dict)


_SOFT_META = {"num_envs": "num_envs", "motion_frames": "motion", "motion_fps": "motion", "motion_sha256": "motion"}
"""Checkpoint meta a resume may change when resume_allow_changes names the config key on the right."""


def meta(trainer: Any) -> dict:
    """What a checkpoint must match to be loaded into this trainer (plain values)."""
    obs = trainer.env.get_observations()
    return {
        "num_envs": int(trainer.env.num_envs),
        "num_actions": int(trainer.env.num_actions),
        "obs_dims": {k: int(v.shape[-1]) for k, v in obs.items()},
        "sampler_kind": str(trainer.sampler.state_dict().get("kind")),
        "num_bins": int(trainer.env.layout.num_bins),
        **motion_meta(trainer.env.reference.motion),
    }

def checkpoint_state(trainer: Any) -> dict:
    """Tensors and plain values only (CHECKPOINT_FORMAT): loads with torch.load(weights_only=True)."""
    state = trainer.alg.save()
    progress = vars(trainer.progress).copy()
    progress["last_eval"] = {str(k): float(v) for k, v in trainer.progress.last_eval.items()}
    state.update(
        iter=int(trainer.progress.iteration),
        progress=progress,
        sampler=trainer.sampler.state_dict(),
        rng=rng_state(),
        format=CHECKPOINT_FORMAT,
        meta=meta(trainer),
        config=json.dumps(trainer.run_config, sort_keys=True, default=str) if trainer.run_config else None,
    )
    return state


def save_checkpoint(trainer: Any) -> Path:
    """Write model_<it>.pt and latest.pt (tables first) and their ONNX exports."""
    from bmimic.training.onnx_export import export_checkpoint_onnx

    it = trainer.progress.iteration
    path = checkpoint_path(trainer.run_dir, it)
    # Tables first (never behind a checkpoint), latest.pt first (never older than a model_<it>.pt).
    trainer.flush_tables()
    state = checkpoint_state(trainer)
    atomic_torch_save(latest_checkpoint(trainer.run_dir), state)
    atomic_torch_save(path, state)
    try:  # policy_<it>.onnx and the BeyondMimic-compatible motion_policy_<it>.onnx
        export_checkpoint_onnx(trainer.alg.get_policy(), trainer.env, checkpoints_dir(trainer.run_dir), it)
    except Exception as e:  # export must never cost a training run
        log.warning("ONNX export failed at iteration %d: %s", it, e)
    return path


def restore(trainer: Any, state: dict, path: str | os.PathLike = "checkpoint", allowed: tuple | list = ()) -> None:
    """Load networks, optimiser, counters, sampler and RNG states; reads the run's tables but writes
    nothing; CheckpointMismatchError (one line) when it does not fit. `allowed` (resume_allow_changes)
    may accept another num_envs or motion; observation and action sizes, sampler kind and bins must
    match (the networks and sampler state depend on them)."""
    saved = state.get("meta")
    if isinstance(saved, dict):
        own = meta(trainer)
        soft = {k: cfg_key for k, cfg_key in _SOFT_META.items() if key_allowed(cfg_key, allowed)}
        differ = [f"{k} {saved[k]} -> {own[k]}" for k in own
                  if k in saved and saved[k] != own[k] and k not in soft]
        if differ:
            raise CheckpointMismatchError(f"{path}: does not fit this run: {'; '.join(differ)}")
    try:
        trainer.alg.load(state, None, strict=True)
    except (RuntimeError, KeyError, ValueError, TypeError) as e:
        raise CheckpointMismatchError(f"{path}: its networks do not fit this config: {mismatch_detail(e)}") from None
    try:
        trainer.sampler.load_state_dict(state["sampler"])
        trainer.progress = Progress(**state["progress"])
        set_rng_state(state["rng"])
    except BmimicError as e:
        raise CheckpointMismatchError(f"{path}: {e}") from None
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        raise CheckpointMismatchError(f"{path}: malformed checkpoint ({type(e).__name__}: {e})") from None
    trainer.runner.current_learning_iteration = trainer.progress.iteration
    trainer.record.truncate(trainer.progress.iteration)
    for key in trainer.total_resets:
        trainer.total_resets[key] = int(sum(_count(r.get(key)) for r in trainer.record.rows("train_metrics")))
    trainer.overflow_world_steps = int(sum(_count(r.get("overflow_worlds")) for r in trainer.record.rows("train_metrics")))
    log.info("resumed from %s at iteration %d (lr %.2e)", path, trainer.progress.iteration, trainer.alg.learning_rate)


def _count(value) -> float:
    """A counter from a table row (absent or NaN in rows written before the column existed: 0)."""
    try:
        return 0.0 if math.isnan(value := float(value)) else value
    except (TypeError, ValueError):
        return 0.0


__all__ = ["Progress", "checkpoint_state", "meta", "restore", "save_checkpoint"]
