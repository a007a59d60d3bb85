"""A trainer's checkpoint: the counters it carries (`Progress`), what it must match (`meta`), what it
holds (networks, optimiser, sampler, RNG, config: `state`), writing it (`save`) and loading one back,
checked, with the run's tables read back (`load`; `RunRecord.truncate`). The Trainer
(bmimic.training.runner) owns one `Checkpoint`, built over itself."""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, Protocol

from bmimic import BmimicError
from bmimic.envs.carry import EnvStateError, env_state, load_env_state
from bmimic.runs.folder import checkpoint_path, checkpoints_dir, latest_checkpoint
from bmimic.runtime import rng_state, set_rng_state
from bmimic.training.checkpoints import (
    CHECKPOINT_FORMAT,
    CheckpointMismatchError,
    atomic_torch_save,
    load_checkpoint_file,
    mismatch_detail,
    motion_meta,
)
from bmimic.training.resume import key_allowed

if TYPE_CHECKING:
    from rsl_rl.runners import OnPolicyRunner

    from bmimic.envs.tracking_env import TrackingEnv
    from bmimic.runs.record import RunRecord
    from bmimic.sampling.base import BinSampler
    from bmimic.training.ppo import GraphPPO

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


class Checkpointed(Protocol):
    """The parts of a trainer that its checkpoint reads and restores (bmimic.training.runner.Trainer)."""

    alg: GraphPPO
    """rsl-rl's PPO (bmimic.training.ppo.GraphPPO): networks and optimiser, save() / load()."""
    runner: OnPolicyRunner
    """rsl-rl's OnPolicyRunner, whose iteration counter a restore sets."""
    env: TrackingEnv
    sampler: BinSampler
    record: RunRecord
    run_dir: Path
    run_config: dict | None
    progress: Progress
    fresh_worlds: bool
    total_resets: dict[str, int]
    overflow_world_steps: int

    def flush_tables(self) -> None: ...


class Checkpoint:
    """The checkpoint of one trainer: built once over it, read and restored through it."""

    def __init__(self, trainer: Checkpointed) -> None:
        self.trainer = trainer

    def meta(self) -> dict:
        """What a checkpoint must match to be loaded into this trainer (plain values)."""
        t = self.trainer
        assert t.env.layout is not None  # a training env's layout is its feedback's
        return {
            "num_envs": int(t.env.num_envs),
            "num_actions": int(t.env.num_actions),
            "obs_dims": t.env.observation_dims(),
            "sampler_kind": str(t.sampler.kind),
            "num_bins": int(t.env.layout.num_bins),
            **motion_meta(t.env.reference.motion),
        }

    def state(self) -> dict:
        """Tensors and plain values only (CHECKPOINT_FORMAT): loads with torch.load(weights_only=True)."""
        t = self.trainer
        state = t.alg.save()
        progress = vars(t.progress).copy()
        progress["last_eval"] = {str(k): float(v) for k, v in t.progress.last_eval.items()}
        state.update(
            iter=int(t.progress.iteration),
            progress=progress,
            sampler=t.sampler.state_dict(),
            rng=rng_state(),
            format=CHECKPOINT_FORMAT,
            meta=self.meta(),
            config=json.dumps(t.run_config, sort_keys=True, default=str) if t.run_config else None,
        )
        if not t.runner.is_distributed:  # under torchrun rank 0 alone saves: the other ranks' worlds are not its
            state["env"] = env_state(t.env)
        return state

    def save(self, final: bool = False) -> Path:
        """Write model_<it>.pt and latest.pt (tables first) and their ONNX exports. A periodic export that
        fails is a warning; the `final` one (the run's deliverable, which its record lists) fails the run
        (BmimicError), so that a run is never `done` without it (a full disk: free space, resume=true)."""
        from bmimic.training.onnx_export import export_checkpoint_onnx

        t = self.trainer
        it = t.progress.iteration
        path = checkpoint_path(t.run_dir, it)
        # Tables first (never behind a checkpoint), latest.pt first (never older than a model_<it>.pt).
        t.flush_tables()
        state = self.state()
        atomic_torch_save(latest_checkpoint(t.run_dir), state)
        atomic_torch_save(path, state)
        try:  # policy_<it>.onnx and the BeyondMimic-compatible motion_policy_<it>.onnx
            export_checkpoint_onnx(t.alg.get_policy(), t.env, checkpoints_dir(t.run_dir), it)
        except Exception as e:  # a periodic export must never cost a training run
            if final:
                raise BmimicError(f"{checkpoints_dir(t.run_dir)}: the ONNX export of the final checkpoint (iteration "
                                  f"{it}) failed ({type(e).__name__}: {e}); the checkpoint itself is written: "
                                  "resume=true writes the export again") from None
            log.warning("ONNX export failed at iteration %d: %s", it, e)
        return path

    def load_file(self, path: str | os.PathLike) -> None:
        """Read a checkpoint (weights_only) and `load` it."""
        self.load(load_checkpoint_file(path, "cpu"), path)

    def load(self, state: dict, path: str | os.PathLike = "checkpoint", allowed: tuple | list = ()) -> None:
        """Load networks, optimiser, counters, sampler and RNG states; reads the run's tables but writes
        nothing; CheckpointMismatchError (one line) when it does not fit. `allowed` (resume_allow_changes)
        may accept another num_envs or motion; observation and action sizes, sampler kind and bins must
        match (the networks and sampler state depend on them)."""
        t = self.trainer
        saved = state.get("meta")
        if isinstance(saved, dict):
            own = self.meta()
            soft = {k: cfg_key for k, cfg_key in _SOFT_META.items() if key_allowed(cfg_key, allowed)}
            differ = [f"{k} {saved[k]} -> {own[k]}" for k in own
                      if k in saved and saved[k] != own[k] and k not in soft]
            if differ:
                raise CheckpointMismatchError(f"{path}: does not fit this run: {'; '.join(differ)}")
        try:
            t.alg.load(state, None, strict=True)
        except (RuntimeError, KeyError, ValueError, TypeError) as e:
            raise CheckpointMismatchError(f"{path}: its networks do not fit this config: {mismatch_detail(e)}") from None
        try:
            t.sampler.load_state_dict(state["sampler"])
            t.progress = Progress(**state["progress"])
            set_rng_state(state["rng"])
        except BmimicError as e:
            raise CheckpointMismatchError(f"{path}: {e}") from None
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise CheckpointMismatchError(f"{path}: malformed checkpoint ({type(e).__name__}: {e})") from None
        self._load_env(state.get("env"), path)
        t.runner.current_learning_iteration = t.progress.iteration
        t.record.truncate(t.progress.iteration)
        rows = t.record.rows("train_metrics")
        for key in t.total_resets:
            t.total_resets[key] = int(sum(_count(r.get(key)) for r in rows))
        t.overflow_world_steps = int(sum(_count(r.get("overflow_worlds")) for r in rows))
        log.info("resumed from %s at iteration %d (lr %.2e)", path, t.progress.iteration, t.alg.learning_rate)


    def _load_env(self, saved: dict | None, path: str | os.PathLike) -> None:
        """The worlds as the checkpoint left them (one process, same num_envs and env config): the resumed
        run then continues exactly as one unbroken run would. Otherwise every world starts afresh, as at a
        run's start (a checkpoint without `env`, under torchrun, or after an allowed change of the env)."""
        t = self.trainer
        why = ("it holds no env state" if saved is None else "the run trains on several GPUs"
               if t.runner.is_distributed else None)
        if saved is not None and why is None:
            try:
                load_env_state(t.env, saved)
                t.fresh_worlds = False
                return
            except EnvStateError as e:
                why = str(e)
        log.warning("%s: the worlds start afresh, not where the checkpoint left them (%s)", path, why)


@contextlib.contextmanager
def rng_untouched() -> Iterator[None]:
    """Run a block (an evaluation) without moving any global random stream: what it draws is undone
    after it, so training draws the same numbers whether or not, and wherever, it evaluated (a run paused
    and evaluated at iteration N continues as an unbroken one)."""
    state = rng_state()
    try:
        yield
    finally:
        set_rng_state(state)


def _count(value) -> float:
    """A counter from a table row (absent or NaN in rows written before the column existed: 0)."""
    try:
        return 0.0 if math.isnan(value := float(value)) else value
    except (TypeError, ValueError):
        return 0.0


__all__ = ["Checkpoint", "Checkpointed", "Progress", "rng_untouched"]
