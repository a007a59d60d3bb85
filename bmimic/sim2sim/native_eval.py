"""sim2sim's evaluation: stratified starts per bin, episodes in native MuJoCo, and the tables of
bmimic.evaluation.tables built from them with the MuJoCo-Warp evaluator's accounting (training.evaluator)."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from bmimic.runs import safe_read
from bmimic.runs.folder import MOTION_POLICY, checkpoints_dir, has_hydra_record
from bmimic.runs.folder import checkpoint_label as run_checkpoint_label
from bmimic.runs.schema import BIN, HORIZON_TRUNCATED, ITERATION
from bmimic.sim2sim.gap import eval_settings, gap_table, restrict, setting_differences, warp_eval
from bmimic.sim2sim.model import build_model
from bmimic.sim2sim.rollout import Episode
from bmimic.sim2sim.run_check import check_policy_of_run
from bmimic.sim2sim.spec import (
    PolicySpec,
    Sim2SimError,
    clip_indices,
    policy_session,
    read_policy,
    read_reference,
)
from bmimic.sim2sim.workers import run_episodes

log = logging.getLogger("bmimic.sim2sim")

MOTION_FILE = MOTION_POLICY
"""File name of the BeyondMimic-compatible export of a checkpoint (bmimic.runs.folder's)."""


def locate(path: str | Path) -> tuple[Path, Path | None]:
    """(BeyondMimic-compatible ONNX, run folder or None) for a run folder or an ONNX file."""
    p = Path(path).expanduser()
    if not p.exists():
        raise Sim2SimError(f"{p}: no such run folder or ONNX file")
    if p.is_file():
        run = p.resolve().parent.parent
        return p.resolve(), run if has_hydra_record(run) else None
    found = [(int(m.group(1)), f) for f in checkpoints_dir(p).glob("motion_policy_*.onnx")
             if (m := MOTION_FILE.search(f.name))]
    if not found:
        raise Sim2SimError(f"{p}: no checkpoints/motion_policy_<it>.onnx (the BeyondMimic-compatible export); "
                           f"write it with: python -m bmimic.export {p}")
    policy = max(found)[1]
    try:
        safe_read.regular_file(policy, p)  # the run's own file: a policy linked from elsewhere is not its result
        return policy.resolve(strict=True), p.resolve()
    except safe_read.UnsafeFileError as e:
        raise Sim2SimError(str(e)) from None
    except (OSError, RuntimeError) as e:  # a dangling link, a loop of links
        raise Sim2SimError(f"{policy}: cannot be read ({e})") from None


def checkpoint_label(spec: PolicySpec) -> str:
    """model_<it> (the name bmimic.eval gives the same checkpoint), else the file stem."""
    if spec.iteration is not None:
        return run_checkpoint_label(spec.iteration)
    m = MOTION_FILE.search(spec.path.name)
    return run_checkpoint_label(int(m.group(1))) if m else spec.path.stem



def collect(episodes: Sequence[Episode], start_bins: np.ndarray, num_frames: int):
    """bmimic.training.evaluator.Rollouts of sim2sim episodes: the rows with their start `bin` first,
    and per motion frame the steps judged at it and their error sums."""
    import pandas as pd

    from bmimic.runs.schema import ERROR_COLUMNS, SMOOTHNESS_COLUMNS
    from bmimic.training.evaluator import Rollouts

    rows = pd.DataFrame([e.row for e in episodes])
    rows.insert(0, BIN, np.asarray(start_bins, dtype=np.int64))
    measured = [*ERROR_COLUMNS, *SMOOTHNESS_COLUMNS]
    sums = np.zeros((num_frames, 1 + len(measured)))
    for e in episodes:
        np.add.at(sums, e.frames, np.column_stack((np.ones(len(e.frames)), e.errors)))
    return Rollouts(rows, pd.DataFrame(sums, columns=["steps", *measured]))


def clip_bins(layout, spec: PolicySpec, clips: Sequence[int]) -> np.ndarray:
    """The bins (ids of the whole motion's layout) of the clips `clips`."""
    first = layout.bin_first_frame.cpu().numpy()
    clip_of_bin = np.searchsorted(spec.clip_starts, first, side="right") - 1
    return np.flatnonzero(np.isin(clip_of_bin, clips))


def evaluate(policy_path: Path, run_dir: Path | None, model: str = "bmimic_g1", episodes_per_bin: int | None = None,
             horizon_s: float | None = None, workers: int = 1, joint_dynamics: str = "model",
             max_mpkpe_rel_mm: float | None = None, clips: Sequence[str] | None = None):
    """Run the sim2sim evaluation; returns (bmimic.evaluation.tables.EvalResult, WarpEval or None, gap table or None).

    Settings not given are the MuJoCo-Warp evaluation's (eval_settings), so the gap compares like with like.
    `clips` (names of a library's clips): only their bins, with the library's bin numbers, compared with
    the same bins of the MuJoCo-Warp evaluation."""
    from bmimic.evaluation.tables import EvalResult, bin_table, episode_table, segment_table
    from bmimic.sampling.layouts import make_layout
    from bmimic.task import check_evaluation_fits
    from bmimic.training.evaluator import stratified_start_frames, summarize

    spec = read_policy(policy_path)
    check_policy_of_run(spec, run_dir)  # before its results are written under the run
    chosen = clip_indices(spec, clips)
    label = checkpoint_label(spec)
    warp = warp_eval(run_dir, label, spec.iteration)
    settings = eval_settings(run_dir, warp, episodes_per_bin, horizon_s, max_mpkpe_rel_mm)
    per_bin = settings["episodes_per_bin"]
    ref = read_reference(policy_session(policy_path), spec, None if clips is None else chosen)
    mjm, model_note = build_model(spec, model, run_dir, joint_dynamics)
    layout = make_layout(spec.bin_layout, spec.num_frames, spec.fps, spec.bin_size_s, clip_starts=spec.clip_starts)
    run_bins = clip_bins(layout, spec, chosen)
    check_evaluation_fits(len(run_bins), per_bin, "--episodes-per-bin")
    frames = stratified_start_frames(layout.bin_first_frame.numpy()[run_bins], layout.bin_num_frames.numpy()[run_bins],
                                     per_bin)
    horizon_steps = max(1, int(round(settings["horizon_s"] / spec.control_dt_s)))
    log.info("sim2sim %s on %s: %d bins%s x %d episodes, horizon %g s, %d workers", policy_path.name, model_note,
             len(run_bins), "" if clips is None else f" of {', '.join(spec.clip_names[k] for k in chosen)}", per_bin,
             settings["horizon_s"], workers)
    runs, wall = run_episodes(policy_path, mjm, spec, ref, frames, horizon_steps, workers, settings["max_mpkpe_rel_mm"])
    rollouts = collect(runs, np.repeat(run_bins, per_bin), spec.num_frames)

    raw = rollouts.episodes
    iteration = -1 if spec.iteration is None else spec.iteration
    episodes = episode_table(raw, layout, ref, spec.control_dt_s, iteration)
    episodes["end_s"] = episodes["end_frame"] / spec.fps
    episodes["end_bin"] = layout.frame_to_bin.numpy()[episodes["end_frame"].to_numpy()]
    episodes["diverged"] = raw["diverged"].to_numpy()
    bins = bin_table(rollouts, episodes, layout, ref.segments)
    segments = segment_table(rollouts, episodes, ref)
    if clips is not None:  # the chosen clips' rows (the other bins and segments were never visited)
        bins = bins[bins[BIN].isin(run_bins)].reset_index(drop=True)
        inside = np.isin(np.searchsorted(spec.clip_starts, np.round(segments["start_s"].to_numpy() * spec.fps),
                                         side="right") - 1, chosen)
        segments = segments[inside].reset_index(drop=True)
        warp = None if warp is None else restrict(warp, run_bins)
    steps = int(raw["steps"].sum())
    worker_s = float(raw["wall_s"].sum())
    summary = {
        **summarize(bins),
        "episodes": int(len(episodes)),
        "failures": int(episodes["failed"].sum()),
        "diverged": int(episodes["diverged"].sum()),
        "num_bins": int(len(run_bins)),
        "clips": [spec.clip_names[k] for k in chosen],
        **settings,
        "horizon_truncated_bins": int(bins[HORIZON_TRUNCATED].sum()),
        "checkpoint": str(policy_path),
        ITERATION: iteration,
        "run_dir": str(run_dir) if run_dir else "",
        "label": label,
        "device": f"cpu, native MuJoCo, {workers} worker process(es)",
        "simulator": "mujoco (C) " + _version("mujoco") + ", onnxruntime " + _version("onnxruntime"),
        "model": model,
        "model_description": model_note,
        "joint_dynamics": joint_dynamics,
        "workers": int(workers),
        "control_steps": steps,
        "physics_steps": steps * spec.decimation,
        "eval_wall_time_s": wall,
        "control_steps_per_s": steps / wall if wall > 0 else math.nan,
        "control_steps_per_s_per_worker": steps / worker_s if worker_s > 0 else math.nan,
    }
    gap = None
    if warp is not None:
        gap = gap_table(bins, warp)
        summary.update(warp_source=warp.source, warp_success_rate=warp.success_rate,
                       warp_mpkpe_rel_mm=warp.mpkpe_rel_mm,
                       gap_success_rate=summary["eval_success_rate"] - warp.success_rate,
                       gap_mpkpe_rel_mm=summary["eval_mpkpe_rel_mm"] - warp.mpkpe_rel_mm,
                       gap_setting_differences=setting_differences(settings, warp))
    result = EvalResult(episodes, bins, segments, summary)
    return result, warp, gap


def _version(module: str) -> str:
    try:
        return str(__import__(module).__version__)
    except (ImportError, AttributeError):
        return "?"
