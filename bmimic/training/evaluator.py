"""Sampler-independent evaluation: stratified start frames in every bin, deterministic policy.

Training-time failure statistics are biased by the sampler (adaptive arms visit hard bins more), so
"when is a bin mastered" is measured here instead: `episodes_per_bin` episodes start at evenly spaced
frames inside each bin and run the deterministic policy for `horizon_s` (or to the end of their clip).

Failures are charged where they happen. A 2 s horizon spans two or three 1 s bins, so per bin:

- `visits`: episodes alive at a frame of the bin at some step (an episode visits every bin from its
  start frame to its last frame; frames advance one per step, so that is a contiguous range);
- `failures`: episodes that failed at a frame of the bin; `failure_rate = failures / visits`;
- `start_episodes`, `start_failures`: the same counted at the bin an episode started in (the old,
  start-bin view);
- `horizon_truncated`: some episode that started in the bin reaches the end of its clip before
  `horizon_s` (the clip's last bins): its failure rate comes from shorter exposure;
- `tracked_through`: episodes that entered the bin from an earlier bin and were still alive at its
  last frame, i.e. tracked all of the bin's frames after a run-up. A horizon-truncated bin counts as
  mastered only when this is at least 1 (bmimic.runs.schema.counts_as_mastered), so the clip's last
  bins are not "mastered" by an untrained policy whose episodes simply run out of clip.

An episode fails when it terminates (any termination but a time-out), when its world breaks (the
simulator's state turns non-finite or leaves its bounds: `broken`, so a policy that blows up the
simulation never scores as tracking), or, with `max_mpkpe_rel_mm` set, when its mean root-relative
MPKPE exceeds it; a termination or break is charged to the frame it happened at, a tracking failure
to the frame with the episode's largest root-relative MPKPE. Tracking errors per bin are means over
the evaluation steps taken at frames of that bin; so are the policy's own smoothness measures
(SMOOTHNESS_COLUMNS: action rate, joint acceleration), which describe the policy, not its tracking.

`aggregate` turns tidy per-episode rows (plus optional per-frame error sums) into the per-bin table;
the Evaluator and any other evaluator (e.g. a native-MuJoCo one) share it.
"""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import numpy as np
import pandas as pd
import torch

from bmimic.envs.measures import smoothness, step_errors
from bmimic.runs.schema import (  # noqa: F401  (the tables' columns, re-exported for the evaluators)
    BIN,
    BIN_COLUMNS,
    ENV_STEPS,
    EPISODE_COLUMNS,
    ERROR_COLUMNS,
    FAILURE_RATE,
    HORIZON_TRUNCATED,
    ITERATION,
    MASTERED_BELOW,
    MPKPE_REL_MM,
    SMOOTHNESS_COLUMNS,
    TRACKED_THROUGH,
    WALL_TIME_S,
    counts_as_mastered,
)
from bmimic.sampling.base import bin_counts
from bmimic.sampling.bins import visits_histogram

REL_MPKPE = ERROR_COLUMNS.index(MPKPE_REL_MM)
ALIVE_CHECK_STEPS = 50
"""A wave of a deterministic evaluation env stops once none of its episodes is alive, checked every
this many steps (one host sync each): a clip rollout (phc, protomotions) otherwise runs the longest
clip's length even when every clip failed in its first second. Outputs are unchanged: steps after the
last episode ended measure nothing. A robust env keeps stepping, as its draws advance torch's generator."""


def stratified_start_frames(bin_first_frame: np.ndarray, bin_num_frames: np.ndarray, per_bin: int) -> np.ndarray:
    """[S * per_bin] frames: per bin, the centres of `per_bin` equal slices of its frames."""
    k = (np.arange(per_bin) + 0.5) / per_bin
    offsets = np.floor(k[None, :] * bin_num_frames[:, None]).astype(np.int64)
    return (bin_first_frame[:, None] + offsets).reshape(-1)


def _counts(bins: np.ndarray, num_bins: int, weights: np.ndarray | None = None) -> np.ndarray:
    w = None if weights is None else torch.as_tensor(np.asarray(weights, dtype=np.int64))
    return bin_counts(torch.as_tensor(bins, dtype=torch.long), num_bins, w).numpy()


def _visits(lo: np.ndarray, hi: np.ndarray, num_bins: int, weights: np.ndarray) -> np.ndarray:
    return visits_histogram(torch.as_tensor(lo, dtype=torch.long), torch.as_tensor(hi, dtype=torch.long), num_bins,
                            torch.as_tensor(np.asarray(weights, dtype=np.int64))).numpy()


def aggregate(episodes: pd.DataFrame, frame_to_bin, frame_errors: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per-bin evaluation table from tidy per-episode rows: one row per bin, columns BIN_COLUMNS, then
    the mean of every error column of `frame_errors` over the steps taken at the bin's frames.

    Args:
        episodes: one row per episode with EPISODE_COLUMNS (`failure_frame`, `terminated`,
            `horizon_truncated` and `broken` may be absent: failures are then charged at `end_frame`,
            all failures count as terminations, no bin is truncated and no world broke).
        frame_to_bin: [F] bin of each motion frame, non-decreasing (BinLayout.frame_to_bin); any
            monotone frame grouping works (e.g. contiguous motion segments).
        frame_errors: optional, one row per frame (F rows): `steps` (evaluation steps taken at that
            frame) and per-step error sums (e.g. `mpkpe_mm`).
    Raises ValueError (one line) on a missing column or a frame outside the motion.
    """
    f2b = np.asarray(frame_to_bin, dtype=np.int64).reshape(-1)
    if not len(f2b) or np.any(np.diff(f2b) < 0):
        raise ValueError("aggregate: frame_to_bin must be a non-empty, non-decreasing array of bins")
    num_frames, num_bins = len(f2b), int(f2b[-1]) + 1
    if f2b[0] != 0 or np.any(np.diff(f2b) > 1):
        raise ValueError("aggregate: every bin 0..S-1 of frame_to_bin must hold at least one frame")
    missing = [c for c in ("start_frame", "end_frame", "failed") if c not in episodes.columns]
    if missing:
        raise ValueError(f"aggregate: episodes lack columns {missing}")
    start = episodes["start_frame"].to_numpy(dtype=np.int64)
    end = episodes["end_frame"].to_numpy(dtype=np.int64)
    if len(start) and (start.min() < 0 or end.max() >= num_frames or np.any(end < start)):
        raise ValueError(f"aggregate: episode frames must satisfy 0 <= start_frame <= end_frame < {num_frames}")
    failed = episodes["failed"].to_numpy(dtype=bool)
    failure_frame = episodes["failure_frame"].to_numpy(dtype=np.int64) if "failure_frame" in episodes else end
    terminated = episodes["terminated"].to_numpy(dtype=bool) if "terminated" in episodes else failed
    truncated = (episodes[HORIZON_TRUNCATED].to_numpy(dtype=bool) if HORIZON_TRUNCATED in episodes
                 else np.zeros(len(start), dtype=bool))
    broken = episodes["broken"].to_numpy(dtype=bool) if "broken" in episodes else np.zeros(len(start), dtype=bool)
    if np.any(broken & ~failed):
        raise ValueError("aggregate: an episode whose world broke must count as failed")
    if np.any(failed & ((failure_frame < start) | (failure_frame > end))):
        raise ValueError("aggregate: a failed episode's failure_frame must lie between its start_frame and end_frame")

    start_bin, end_bin = f2b[start], f2b[end]
    fail_bin = f2b[np.where(failed, failure_frame, start)]
    bin_last = np.searchsorted(f2b, np.arange(num_bins), side="right") - 1
    # Bins an episode covered completely after entering from an earlier bin: from the one after its
    # start bin to its end bin (that one only when the episode was still alive at its last frame).
    through_hi = end_bin - (end < bin_last[end_bin])
    through = through_hi >= start_bin + 1
    through_lo = np.minimum(start_bin + 1, num_bins - 1)  # in range even where `through` is false
    out = pd.DataFrame({
        BIN: np.arange(num_bins),
        "visits": _visits(start_bin, end_bin, num_bins, np.ones(len(start))),
        "failures": _counts(fail_bin, num_bins, failed),
        "start_episodes": _counts(start_bin, num_bins),
        "start_failures": _counts(start_bin, num_bins, failed),
        "terminations": _counts(fail_bin, num_bins, failed & terminated & ~broken),
        "tracking_failures": _counts(fail_bin, num_bins, failed & ~terminated & ~broken),
        "broken": _counts(fail_bin, num_bins, broken),
        HORIZON_TRUNCATED: _counts(start_bin, num_bins, truncated) > 0,
        TRACKED_THROUGH: _visits(through_lo, np.maximum(through_hi, through_lo), num_bins, through),
    })
    with np.errstate(invalid="ignore", divide="ignore"):
        out.insert(3, FAILURE_RATE, out["failures"] / out["visits"].where(out["visits"] > 0))
    if frame_errors is None:
        out["eval_steps"] = 0
        return out
    if len(frame_errors) != num_frames or "steps" not in frame_errors:
        raise ValueError(f"aggregate: frame_errors needs {num_frames} rows (one per frame) and a steps column")
    sums = frame_errors.groupby(f2b).sum()
    out["eval_steps"] = sums["steps"].to_numpy().astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        for c in frame_errors.columns.drop("steps"):
            out[c] = sums[c].to_numpy() / out["eval_steps"].where(out["eval_steps"] > 0).to_numpy()
    return out


class Rollouts(NamedTuple):
    """What one evaluation pass produced."""

    episodes: pd.DataFrame
    """One row per episode: `bin` (its start bin), EPISODE_COLUMNS, `error_failed`, `broken` (the
    training evaluator's) and the episode's mean of every ERROR_COLUMNS (and SMOOTHNESS_COLUMNS)
    entry over its alive steps."""
    frame_errors: pd.DataFrame
    """One row per motion frame: `steps` taken at it and the per-step sums of ERROR_COLUMNS (and
    SMOOTHNESS_COLUMNS)."""


def segment_of_bin(layout, segments) -> list[str]:
    """Label of each bin of a BinLayout: the segment covering the bin's midpoint ('' where none does)."""
    edges = layout.edges_s.cpu().numpy()
    labels = []
    for b in range(layout.num_bins):
        mid = 0.5 * (edges[b] + edges[b + 1])
        name = ""
        for seg in segments:
            if seg.start_s <= mid < seg.end_s or (b == layout.num_bins - 1 and seg.end_s >= mid):
                name = seg.name
                break
        labels.append(name)
    return labels


def bin_table(rollouts: Rollouts, layout, segments) -> pd.DataFrame:
    """`aggregate` of one evaluation (from any evaluator) with the bins' edges and segment labels."""
    per_bin = aggregate(rollouts.episodes, layout.frame_to_bin.cpu().numpy(), rollouts.frame_errors)
    edges = layout.edges_s.cpu().numpy()
    labels = segment_of_bin(layout, segments)
    per_bin.insert(1, "bin_start_s", edges[per_bin[BIN]])
    per_bin.insert(2, "bin_end_s", edges[per_bin[BIN] + 1])
    per_bin.insert(3, "segment", [labels[b] for b in per_bin[BIN]])
    per_bin.insert(4, "clip", clip_of_bins(layout, per_bin[BIN]))
    return per_bin


def clip_of_bins(layout, bins) -> list[str]:
    """The name of the clip each bin belongs to (a single motion: its name)."""
    names = getattr(layout, "clip_names", ("motion",))
    clip = layout.bin_clip.cpu().numpy() if hasattr(layout, "bin_clip") else None
    return [names[int(clip[b])] if clip is not None else names[0] for b in bins]


class Evaluator:
    """Runs evaluation episodes in a dedicated `mode="eval"` environment (robust: with DR, noise, pushes)."""

    def __init__(self, env, layout, segments, episodes_per_bin: int, horizon_s: float,
                 max_mpkpe_rel_mm: float | None = None) -> None:
        self.env = env
        self.layout = layout
        self.segments = list(segments)
        first = layout.bin_first_frame.cpu().numpy()
        count = layout.bin_num_frames.cpu().numpy()
        self.frames = stratified_start_frames(first, count, episodes_per_bin)
        self.bins = np.repeat(np.arange(layout.num_bins), episodes_per_bin)
        self.horizon_steps = max(1, int(round(horizon_s / env.step_dt)))
        self.max_mpkpe_rel_mm = max_mpkpe_rel_mm
        self.before_wave = None
        """Called with each wave's index before its episodes start (whole clips: a robust wave's own draws)."""
        self.stop_early: bool | None = None
        """Whether a wave may stop once no episode is alive (ALIVE_CHECK_STEPS); None: unless the env is robust."""
        self.seconds_per_step = math.nan
        """Wall time per control step of the last wave (its steps to its rows on the host)."""

    def segment_of_bin(self) -> list[str]:
        """Label of each bin: the segment covering the bin's midpoint ('' without a manifest)."""
        return segment_of_bin(self.layout, self.segments)

    @torch.inference_mode()
    def run_episodes(self, policy) -> Rollouts:
        """Every evaluation episode, in waves of the env's size; no host synchronisation per step."""
        env = self.env
        n, dev = env.num_envs, env.device
        frame_to_bin = self.layout.frame_to_bin
        num_frames = int(frame_to_bin.shape[0])
        measured = (*ERROR_COLUMNS, *SMOOTHNESS_COLUMNS)
        frame_sums = torch.zeros(num_frames, len(measured) + 1, device=dev)  # steps, then per-step sums
        rows = []
        may_stop = not env.perturbed if self.stop_early is None else self.stop_early
        for first in range(0, len(self.frames), n):
            if self.before_wave is not None:
                self.before_wave(first // n)
            frames = self.frames[first : first + n]
            m = len(frames)
            padded = np.concatenate([frames, np.full(n - m, frames[-1])])
            env.reset_to_frames(torch.as_tensor(padded, device=dev))
            alive = torch.arange(n, device=dev) < m
            start = env.time_steps.clone()
            # Steps an episode can take before its clip ends (reached_clip_end stops it after them).
            truncated = (env.segment_end - 1 - start) < self.horizon_steps
            end_frame = start.clone()
            worst_frame = start.clone()
            worst_rel = torch.full((n,), -1.0, device=dev)
            terminated = torch.zeros(n, dtype=torch.bool, device=dev)
            broken = torch.zeros(n, dtype=torch.bool, device=dev)
            steps = torch.zeros(n, device=dev)
            sums = torch.zeros(n, len(measured), device=dev)
            obs = env.get_observations()
            t0, taken = time.perf_counter(), 0
            for step in range(self.horizon_steps):
                taken = step + 1
                frame = env.time_steps.clone()  # the frame this step is judged at (terminations)
                end_frame = torch.where(alive, frame, end_frame)
                prev_joint_vel = env.state.joint_vel.clone()
                actions = policy(obs, stochastic_output=False)
                obs, _, _, extras = env.step(actions)
                broke = extras["broken"] & alive
                # A world that broke was put back at the initial pose: its errors this step are not
                # the policy's tracking, so the step is not measured (the episode fails here).
                measured_f = (alive & ~broke).float()[:, None]
                err = torch.cat((step_errors(env), smoothness(env, prev_joint_vel)), dim=-1)
                err = torch.where(measured_f > 0, err, 0.0)
                sums += err
                steps += measured_f[:, 0]
                frame_sums.index_add_(0, frame, torch.cat((measured_f, err), dim=-1))
                worse = (measured_f[:, 0] > 0) & (err[:, REL_MPKPE] > worst_rel)
                worst_rel = torch.where(worse, err[:, REL_MPKPE], worst_rel)
                worst_frame = torch.where(worse, frame, worst_frame)
                terminated |= extras["terminated"] & alive
                broken |= broke
                stop = (extras["terminated"] | extras["broken"]) & alive
                # An episode that reaches the end of its clip tracked up to the clip's last frame.
                end_frame = torch.where(alive & ~stop & env.reached_clip_end, env.time_steps, end_frame)
                alive &= ~stop & ~env.reached_clip_end
                if may_stop and (step + 1) % ALIVE_CHECK_STEPS == 0 and not bool(alive.any()):
                    break
            means = sums / steps.clamp_min(1)[:, None]
            error_failed = torch.zeros_like(terminated)
            if self.max_mpkpe_rel_mm is not None:
                error_failed = ~terminated & ~broken & (means[:, REL_MPKPE] > self.max_mpkpe_rel_mm)
            ended = terminated | broken
            failed = ended | error_failed
            failure_frame = torch.where(ended, end_frame, torch.where(error_failed, worst_frame, -1))
            columns = {"start_frame": start, "end_frame": end_frame, "failed": failed, "failure_frame": failure_frame,
                       "terminated": terminated, "error_failed": error_failed, "steps": steps,
                       HORIZON_TRUNCATED: truncated, "broken": broken}
            # One host transfer for the wave's per-episode columns, then each back under its name and type.
            host = torch.stack([c.long() for c in columns.values()], dim=-1)[:m].cpu().numpy()
            self.seconds_per_step = (time.perf_counter() - t0) / max(taken, 1)
            wave = pd.DataFrame(means[:m].cpu().numpy(), columns=list(measured))
            head = pd.DataFrame({BIN: self.bins[first : first + m], **{
                name: host[:, j].astype(bool) if c.dtype == torch.bool else host[:, j]
                for j, (name, c) in enumerate(columns.items())}})
            rows.append(pd.concat([head, wave], axis=1))
        frame_errors = pd.DataFrame(frame_sums.double().cpu().numpy(), columns=["steps", *measured])
        return Rollouts(pd.concat(rows, ignore_index=True), frame_errors)

    def bin_table(self, rollouts: Rollouts) -> pd.DataFrame:
        """`aggregate` of one evaluation with the bins' edges and segment labels."""
        return bin_table(rollouts, self.layout, self.segments)

    def evaluate(self, policy, iteration: int, env_steps: int, wall_time_s: float) -> pd.DataFrame:
        """Per-bin table (eval.parquet rows) for one evaluation."""
        per_bin = self.bin_table(self.run_episodes(policy))
        per_bin.insert(0, WALL_TIME_S, float(wall_time_s))
        per_bin.insert(0, ENV_STEPS, int(env_steps))
        per_bin.insert(0, ITERATION, int(iteration))
        return per_bin


def summarize(per_bin: pd.DataFrame, prefix: str = "eval") -> dict[str, float]:
    """Overall numbers of one evaluation: the fraction of episodes that failed (each failure is charged
    to exactly one bin, so it is failures / start_episodes summed), the number of episodes whose world
    broke (`broken`, part of the failures), the fraction of bins mastered (counts_as_mastered at
    MASTERED_BELOW) and step-weighted means of the errors and smoothness measures (NaN where the
    table lacks a column). Keys `<prefix>_...`."""
    episodes = int(per_bin["start_episodes"].sum())
    steps = per_bin["eval_steps"].to_numpy(dtype=float)
    out = {
        f"{prefix}_failure_rate": float(per_bin["failures"].sum() / max(episodes, 1)),
        f"{prefix}_bins_mastered_frac": float(counts_as_mastered(per_bin, MASTERED_BELOW).mean()),
    }
    out[f"{prefix}_success_rate"] = 1.0 - out[f"{prefix}_failure_rate"]
    out[f"{prefix}_broken"] = float(per_bin["broken"].sum()) if "broken" in per_bin else math.nan
    for c in (*ERROR_COLUMNS, *SMOOTHNESS_COLUMNS):
        if c in per_bin and steps.sum() > 0:
            ok = steps > 0
            out[f"{prefix}_{c}"] = float(np.average(per_bin[c].to_numpy(dtype=float)[ok], weights=steps[ok]))
        else:
            out[f"{prefix}_{c}"] = math.nan
    return out

