"""Whole-clip evaluation: rollouts from each clip's first frame to its last, deterministic policy, under
named conditions (bmimic.runs.schema.WHOLE_CLIP_CONDITIONS).

It generalises the PHC / ProtoMotions signal (bmimic.training.clip_rollouts: one rollout per clip from
its first frame) to R rollouts per clip and no time cap: `nominal` runs in an evaluation environment
without perturbations, as the window evaluation does, and is deterministic (every rollout from a clip's
first frame would be the same), so it runs one rollout per clip; `robust` runs R per clip in an
environment with training's domain randomisation, observation noise and pushes, every rollout in a
world of its own draw. The environments' episode limit is derived so that the longest clip fits
(bmimic.task.build_whole_clip), and a clip longer than `eval.whole_clip.max_clip_s` is refused there:
no rollout is ever cut short, and one that neither failed nor reached its clip's last frame is an error.

A robust evaluation draws from its own random stream, seeded by the run's seed and the wave: it neither
moves training's stream nor depends on when it runs, so every evaluation of a run sees the same draws
(common random numbers over training) and `bmimic.eval --whole-clip` of a checkpoint repeats them.

Per clip and condition the tables (runs.schema's WHOLE_CLIP_* columns) give the fraction of rollouts
that completed the clip, the survival curve (rollouts still tracking at every second), where the
failed ones failed (frame, time, bin), failures within the first START_TRANSIENT_S seconds (start
transients) apart from later ones, and the tracking errors over the completed rollouts.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import pandas as pd
import torch

from bmimic.runs.schema import (
    BIN,
    CONDITION,
    CONDITIONS,
    ERROR_COLUMNS,
    SMOOTHNESS_COLUMNS,
    START_TRANSIENT_S,
    WHOLE_CLIP_COLUMNS,
    WHOLE_CLIP_FAILURE_COLUMNS,
    WHOLE_CLIP_SUCCESS,
    condition_rollouts,
    whole_clip_key,
    whole_clip_survival,
)
from bmimic.training.clip_rollouts import clip_bounds, clip_start_rollouts

SEED_OFFSET = 7919
"""Added to the run's seed for the robust condition's stream (apart from the run's own)."""


@dataclass
class WholeClipResult:
    """One whole-clip evaluation, every condition."""

    clips: pd.DataFrame
    """WHOLE_CLIP_COLUMNS then the error and smoothness means over the completed rollouts."""
    survival: pd.DataFrame
    """WHOLE_CLIP_SURVIVAL_COLUMNS (bmimic.runs.schema.whole_clip_survival of the other two)."""
    failures: pd.DataFrame
    """WHOLE_CLIP_FAILURE_COLUMNS: one row per failed rollout."""
    summary: dict
    """whole_clip_key(condition, key) for WHOLE_CLIP_SUMMARY_KEYS, every condition."""


def clip_tables(episodes: pd.DataFrame, condition: str, layout, step_dt: float, evaluation_s: float = math.nan
                ) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """The clips, survival and failure tables of one condition from clip_start_rollouts' episodes (any
    evaluator's rows with `clip`, `rollout`, start, end and failure frames, `failed`, `terminated`,
    `broken`, `steps` and the error means). Raises ValueError for a rollout that neither failed nor
    reached its clip's last frame (a rollout cut short)."""
    starts, ends = clip_bounds(layout)
    names = list(getattr(layout, "clip_names", ("motion",)))[: len(starts)]
    clip = episodes["clip"].to_numpy(dtype=np.int64)
    start = episodes["start_frame"].to_numpy(dtype=np.int64)
    end = episodes["end_frame"].to_numpy(dtype=np.int64)
    failed = episodes["failed"].to_numpy(dtype=bool)
    broken = episodes["broken"].to_numpy(dtype=bool)
    terminated = episodes["terminated"].to_numpy(dtype=bool) & ~broken
    completed = ~failed & (end == ends[clip] - 1)
    if np.any(~failed & ~completed):
        raise ValueError(f"whole clip: {int(np.sum(~failed & ~completed))} rollouts neither failed nor reached their "
                         "clip's last frame (cut short)")
    fail_frame = episodes["failure_frame"].to_numpy(dtype=np.int64)
    offset = fail_frame - start  # frames into the clip at which each failed rollout failed
    transient = failed & (offset * step_dt < START_TRANSIENT_S)
    steps = episodes["steps"].to_numpy(dtype=float)
    measured = [c for c in (*ERROR_COLUMNS, *SMOOTHNESS_COLUMNS) if c in episodes]

    def per_clip(mask: np.ndarray) -> np.ndarray:
        return np.bincount(clip, weights=mask.astype(float), minlength=len(starts)).astype(np.int64)

    rows = {CONDITION: condition, "clip": np.arange(len(starts)), "clip_name": names,
            "clip_duration_s": (ends - starts - 1) * step_dt, "rollouts": per_clip(np.ones(len(clip), bool)),
            "completed": per_clip(completed)}
    with np.errstate(invalid="ignore", divide="ignore"):
        rows[WHOLE_CLIP_SUCCESS] = rows["completed"] / np.where(rows["rollouts"] > 0, rows["rollouts"], np.nan)
        rows.update(failures=per_clip(failed), transient_failures=per_clip(transient),
                    later_failures=per_clip(failed & ~transient), terminations=per_clip(failed & terminated),
                    tracking_failures=per_clip(failed & ~terminated & ~broken), broken=per_clip(failed & broken),
                    evaluation_s=float(evaluation_s))
        done_steps = np.bincount(clip, weights=np.where(completed, steps, 0.0), minlength=len(starts))
        for col in measured:
            sums = np.bincount(clip, weights=np.where(completed, episodes[col].to_numpy(float) * steps, 0.0),
                               minlength=len(starts))
            rows[col] = sums / np.where(done_steps > 0, done_steps, np.nan)
    clips = pd.DataFrame(rows, columns=[*WHOLE_CLIP_COLUMNS, *measured])

    f = np.flatnonzero(failed)
    failures = pd.DataFrame({CONDITION: condition, "clip": clip[f], "clip_name": [names[i] for i in clip[f]],
                             "rollout": episodes["rollout"].to_numpy(dtype=np.int64)[f], "failure_frame": fail_frame[f],
                             "failure_time_s": offset[f] * step_dt, BIN: layout.frame_to_bin.cpu().numpy()[fail_frame[f]],
                             "transient": transient[f], "terminated": terminated[f], "broken": broken[f]},
                            columns=list(WHOLE_CLIP_FAILURE_COLUMNS))
    return clips, whole_clip_survival(clips, failures), failures


def summarize_whole_clip(clips: pd.DataFrame) -> dict[str, float]:
    """Per condition of `clips`: whole_clip_key(condition, ...) of the success over every rollout of every
    clip, the counts, and the errors over the completed rollouts (weighted by the clips' durations x completed
    rollouts, i.e. by steps)."""
    out = {}
    for condition, g in clips.groupby(CONDITION, sort=False):
        rollouts, completed = int(g["rollouts"].sum()), int(g["completed"].sum())
        out[whole_clip_key(condition, "success_rate")] = completed / rollouts if rollouts else math.nan
        for key in ("rollouts", "completed", "transient_failures", "later_failures", "broken"):
            out[whole_clip_key(condition, key)] = int(g[key].sum())
        weight = (g["completed"] * g["clip_duration_s"]).to_numpy(dtype=float)
        for c in ERROR_COLUMNS:
            ok = np.isfinite(g[c].to_numpy(dtype=float)) & (weight > 0) if c in g else np.zeros(len(g), bool)
            out[whole_clip_key(condition, c)] = (float(np.average(g[c].to_numpy(dtype=float)[ok], weights=weight[ok]))
                                                 if ok.any() else math.nan)
    return out


@contextlib.contextmanager
def own_random_stream(seed: int, device: str):
    """torch's generators (CPU, and `device`'s if CUDA) seeded with `seed` for the block and restored after
    it: what the block draws leaves the caller's stream where it was."""
    dev = torch.device(device)
    with torch.random.fork_rng(devices=[dev.index or 0] if dev.type == "cuda" else []):
        torch.manual_seed(seed)
        yield


class WholeClipEvaluation:
    """`conditions` of whole-clip rollouts; `make(condition, per_clip)` builds the condition's Evaluator
    (bmimic.task.build_whole_clip), on first use, and it is kept for the next evaluation."""

    def __init__(self, make: Callable, layout, conditions: list[str], rollouts: int, seed: int, device: str) -> None:
        self.make, self.layout, self.device = make, layout, device
        self.conditions = list(conditions)
        self.rollouts = int(rollouts)
        """Rollouts per clip of a perturbed condition (nominal: one)."""
        self.seed = int(seed) + SEED_OFFSET
        self.evaluators: dict = {}

    def per_clip(self, condition: str) -> int:
        """Rollouts per clip under `condition`: one when it is deterministic."""
        return condition_rollouts(condition, self.rollouts)

    def steps(self) -> int:
        """Control steps of the longest clip (one wave lasts that long)."""
        starts, ends = clip_bounds(self.layout)
        return int((ends - starts).max()) - 1

    def evaluator(self, condition: str):
        """The condition's Evaluator (built on first use, then kept)."""
        if condition not in self.evaluators:
            self.evaluators[condition] = self.make(condition, self.per_clip(condition))
        return self.evaluators[condition]

    def build(self) -> None:
        """Build every condition's environment now (training: before the first iteration, beside the
        window evaluator, rather than between captured training steps), drawing from their own stream."""
        with own_random_stream(self.seed, self.device):
            for condition in self.conditions:
                self.evaluator(condition)

    def _redraw(self, ev, wave: int) -> None:
        """A robust wave's own draws: the worlds' domain randomisation and push timers drawn anew from a
        stream seeded by the run's seed and the wave (whatever ran before)."""
        torch.manual_seed(self.seed + 1_000_003 * wave)
        ev.env.redraw_startup_events()

    def evaluate(self, policy) -> WholeClipResult:
        """Every condition's rollouts and tables (the deterministic policy: pass it in eval mode)."""
        parts = []
        for condition in self.conditions:
            t0 = time.perf_counter()
            perturbed = CONDITIONS[condition].perturbed
            with own_random_stream(self.seed, self.device) if perturbed else contextlib.nullcontext():
                ev = self.evaluator(condition)
                ev.stop_early = True  # draws are per wave (own stream), so stopping early changes nothing measured
                ev.before_wave = (lambda wave, ev=ev: self._redraw(ev, wave)) if perturbed else None
                episodes = clip_start_rollouts(ev, policy, self.per_clip(condition)).episodes
            parts.append(clip_tables(episodes, condition, self.layout, ev.env.step_dt, time.perf_counter() - t0))
        clips, survival, failures = (pd.concat(p, ignore_index=True) for p in zip(*parts))
        return WholeClipResult(clips, survival, failures, summarize_whole_clip(clips))

    def close(self) -> None:
        """Release the environments' graphs."""
        for ev in self.evaluators.values():
            ev.env.close()


__all__ = ["WholeClipEvaluation", "WholeClipResult", "clip_tables", "own_random_stream", "summarize_whole_clip"]
