"""Whole-clip rollouts of the exported policy in native MuJoCo (`python -m bmimic.sim2sim RUN --whole-clip R`).

Each rollout starts at a clip's first frame, from the reference state, and runs the deterministic
policy to the clip's last frame unless it fails first (sim2sim's failure rule: a termination, a
broken world, or with --max-mpkpe-rel-mm a mean root-relative MPKPE above it). Conditions
(runs.schema.WHOLE_CLIP_CONDITIONS):

- `nominal`: no perturbation. Native MuJoCo and onnxruntime run single-threaded and the start is
  exact, so every nominal rollout of a clip is the same rollout: one is run per clip, not R.
- `robust`: training's perturbations that native MuJoCo supports (bmimic.sim2sim.perturb: observation
  noise, pushes, foot friction, centre-of-mass and default-pose offsets) with the magnitudes and
  intervals of the run's env config; R rollouts per clip, each with its own seeded draw
  (`--seed`, the clip and the rollout's index).

Per condition: the rollouts that completed each clip, the survival over clip time (the fraction still
tracking at every whole second and at the last frame), where the failures happened (each rollout's
failure frame, time and bin; per bin, failures per visit as in sim2sim's window evaluation), start
transients (failures within START_TRANSIENT_S of the start) apart from later failures, and the
tracking errors over the completed rollouts; and, when the run folder holds one, the gap to bmimic's
own (MuJoCo-Warp) whole-clip success of the same checkpoint (bmimic.sim2sim.whole_clip_gap).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence, cast

import numpy as np
import pandas as pd

from bmimic.runs import safe_read
from bmimic.runs.folder import HYDRA_DIR, RESOLVED_CONFIG, read_resolved_config
from bmimic.runs.schema import (
    CONDITIONS,
    ERROR_COLUMNS,
    ITERATION,
    START_TRANSIENT_S,
    WHOLE_CLIP_CONDITIONS,
    WHOLE_CLIP_ROLLOUT_COLUMNS,
    condition_rollouts,
    whole_clip_survival,
)
from bmimic.sim2sim.model import build_model
from bmimic.sim2sim.native_eval import checkpoint_label, collect
from bmimic.sim2sim.perturb import Perturbations, perturbations_from_env
from bmimic.sim2sim.run_check import check_policy_of_run
from bmimic.sim2sim.spec import (
    PolicySpec,
    Sim2SimError,
    clip_indices,
    first_line,
    policy_session,
    read_policy,
    read_reference,
)
from bmimic.sim2sim.whole_clip_gap import clip_spans, gap_table, warp_whole_clip
from bmimic.sim2sim.workers import EpisodeTask, run_tasks

log = logging.getLogger("bmimic.sim2sim")


def parse_conditions(text: str) -> tuple[str, ...]:
    """`nominal,robust` -> the conditions in that order; an unknown or repeated name is refused."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in WHOLE_CLIP_CONDITIONS]
    if not names or unknown or len(set(names)) != len(names):
        raise Sim2SimError(f"--conditions {text!r}: expected a comma-separated subset of "
                           f"{', '.join(WHOLE_CLIP_CONDITIONS)} without repeats"
                           + (f" ({', '.join(map(repr, unknown))} unknown)" if unknown else ""))
    return names


def check_rollouts(rollouts: int) -> int:
    if rollouts < 1:
        raise Sim2SimError(f"--whole-clip {rollouts}: the rollouts per clip must be >= 1")
    return rollouts


def run_config_section(run_dir: Path | None, key: str) -> tuple[dict | None, str]:
    """(section `key` of the run's config, where it was read): resolved_config.json, else Hydra's
    .hydra/config.yaml (runs written before resolved_config.json); (None, "") when neither has it."""
    if run_dir is None:
        return None, ""
    section = (read_resolved_config(run_dir) or {}).get(key)
    if isinstance(section, dict):
        return section, f"{run_dir / RESOLVED_CONFIG} ({key})"
    composed = run_dir / HYDRA_DIR / "config.yaml"
    if not composed.is_file():
        return None, ""
    from omegaconf import DictConfig, OmegaConf

    try:
        section = OmegaConf.to_container(cast(DictConfig, OmegaConf.create(safe_read.read_yaml_text(composed)))[key], resolve=True)
    except Exception as e:  # omegaconf raises many types; all mean the same to the user
        raise Sim2SimError(f"{composed}: its {key} config is unreadable: {first_line(e)}") from None
    return (section, f"{composed} ({key})") if isinstance(section, dict) else (None, "")


def clip_names(run_dir: Path | None, spec: PolicySpec) -> list[str]:
    """The clips' names as the file records them (motion_clip_names); a file exported before it holds
    clip0, clip1, ..., and a single clip of it is named after the run's motion."""
    motion = run_config_section(run_dir, "motion")[0] or {}
    if spec.clip_names == ["clip0"] and motion.get("name"):
        return [str(motion["name"])]
    return list(spec.clip_names)


def robust_perturbations(run_dir: Path | None, spec: PolicySpec) -> Perturbations:
    """The robust condition of the run's env config, or of bmimic's default env config for an ONNX file
    without its run folder."""
    env, source = run_config_section(run_dir, "env")
    if env is not None:
        return perturbations_from_env(env, spec, source)
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from bmimic import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("train")
    return perturbations_from_env(cast(dict, OmegaConf.to_container(cfg.env, resolve=True)), spec,
                                  "bmimic's default env config (no run config found)")


# ============================================================================================ tables
def rollout_table(episodes: pd.DataFrame, raw: pd.DataFrame, condition: str, clips: np.ndarray, names: list[str],
                  starts: np.ndarray, ends: np.ndarray, fps: float) -> pd.DataFrame:
    """sim2sim's episode rows (bmimic.evaluation.tables.episode_table) with WHOLE_CLIP_ROLLOUT_COLUMNS
    first: the condition, clip, rollout index, whether it completed the clip, when it failed (seconds
    into the clip; NaN if it did not) and whether that was a start transient, and its pushes."""
    failed = episodes["failed"].to_numpy(dtype=bool)
    failure_s = np.where(failed, (episodes["failure_frame"].to_numpy() - starts[clips]) / fps, np.nan)
    rollout = np.zeros(len(clips), dtype=np.int64)
    for c in np.unique(clips):
        rollout[clips == c] = np.arange(int((clips == c).sum()))
    front = pd.DataFrame({
        "condition": condition, "clip": clips, "clip_name": [names[c] for c in clips], "rollout": rollout,
        "completed": ~failed & (episodes["end_frame"].to_numpy() == ends[clips] - 1),
        "failure_time_s": failure_s, "transient": failed & (failure_s < START_TRANSIENT_S),
        "pushes": raw["pushes"].to_numpy(dtype=np.int64) if "pushes" in raw else np.zeros(len(clips), dtype=np.int64),
    }, columns=list(WHOLE_CLIP_ROLLOUT_COLUMNS))
    return pd.concat([front, episodes.drop(columns=["episode"])], axis=1)


def survival_table(rollouts: pd.DataFrame, durations_s: np.ndarray) -> pd.DataFrame:
    """Per condition and clip, at every whole second of the clip and at its last frame: the rollouts
    still tracking (not failed at or before that time) and their fraction (WHOLE_CLIP_SURVIVAL_COLUMNS;
    bmimic.runs.schema.whole_clip_survival, the rule bmimic's own whole-clip tables follow)."""
    clips = rollouts.groupby(["condition", "clip"], sort=False).agg(
        clip_name=("clip_name", "first"), rollouts=("clip_name", "size")).reset_index()
    clips["clip_duration_s"] = np.asarray(durations_s, dtype=float)[clips["clip"].to_numpy(dtype=np.int64)]
    failed = rollouts[rollouts["failure_time_s"].notna()]
    return whole_clip_survival(clips, failed)


def condition_summary(rollouts: pd.DataFrame) -> dict:
    """One condition's numbers over every clip: rollouts, completed and their fraction (whole-clip
    success), failures split into start transients and later ones, broken worlds, pushes, and the
    step-weighted tracking errors over the completed rollouts (NaN when none completed)."""
    completed = rollouts[rollouts["completed"]]
    failed = rollouts["failed"].to_numpy(dtype=bool)
    steps = completed["steps"].to_numpy(dtype=float)
    errors = {c: float(np.average(completed[c], weights=steps)) if steps.sum() > 0 else math.nan for c in ERROR_COLUMNS}
    return {
        "rollouts": int(len(rollouts)), "completed": int(rollouts["completed"].sum()),
        "success_rate": float(rollouts["completed"].mean()) if len(rollouts) else math.nan,
        "failures": int(failed.sum()), "transient_failures": int(rollouts["transient"].sum()),
        "later_failures": int((failed & ~rollouts["transient"].to_numpy(dtype=bool)).sum()),
        "broken": int(rollouts["broken"].sum()), "pushes_per_rollout": float(rollouts["pushes"].mean()),
        "mean_survival_s": float(rollouts["survival_s"].mean()),
        **errors,
    }


# ============================================================================================ the evaluation
@dataclass
class WholeClipResult:
    """The whole-clip rollouts of one checkpoint, as tables (written by bmimic.runs.record.write_evaluation)."""

    rollouts: pd.DataFrame
    """One row per rollout (WHOLE_CLIP_ROLLOUT_COLUMNS, then sim2sim's episode columns)."""
    bins: pd.DataFrame
    """Per condition and bin: visits and failures where they happened (sim2sim's bin table)."""
    segments: pd.DataFrame
    """Per condition and motion segment, counted like the bins."""
    survival: pd.DataFrame
    """Per condition, clip and second: rollouts still tracking (WHOLE_CLIP_SURVIVAL_COLUMNS)."""
    summary: dict
    """Per condition (`conditions`), the settings, the perturbations and the gap."""
    gap: pd.DataFrame
    """Per condition and clip: native success, bmimic's where known, the difference."""


def run_whole_clip(policy_path: Path, run_dir: Path | None, rollouts_per_clip: int,
                   conditions: Sequence[str] = WHOLE_CLIP_CONDITIONS, model: str = "bmimic_g1", workers: int = 1,
                   joint_dynamics: str = "model", max_mpkpe_rel_mm: float | None = None, seed: int = 0,
                   clips: Sequence[str] | None = None) -> WholeClipResult:
    """R whole-clip rollouts per clip and condition (module docstring); `clips`: of those clips of a
    library alone (only their frames are read; each rollout draws what it would in a run of every clip)."""
    from bmimic.evaluation.tables import bin_table, episode_table, segment_table
    from bmimic.sampling.layouts import make_layout

    check_rollouts(rollouts_per_clip)
    spec = read_policy(policy_path)
    check_policy_of_run(spec, run_dir)  # before its results are written under the run
    chosen = np.asarray(clip_indices(spec, clips), dtype=np.int64)
    label = checkpoint_label(spec)
    ref = read_reference(policy_session(policy_path), spec, None if clips is None else chosen.tolist())
    mjm, model_note = build_model(spec, model, run_dir, joint_dynamics)
    layout = make_layout(spec.bin_layout, spec.num_frames, spec.fps, spec.bin_size_s, clip_starts=spec.clip_starts)
    starts, ends = clip_spans(spec)
    names = clip_names(run_dir, spec)
    durations_s = (ends - 1 - starts) / spec.fps
    iteration = -1 if spec.iteration is None else spec.iteration
    robust = robust_perturbations(run_dir, spec) if any(CONDITIONS[c].perturbed for c in conditions) else None
    if robust is not None and robust.skipped:
        log.warning("robust: env.events terms without a native version, not applied: %s", ", ".join(robust.skipped))
    tables: dict[str, list[pd.DataFrame]] = {"rollouts": [], "bins": [], "segments": []}
    per_condition, wall_s = {}, {}
    for condition in conditions:
        perturbed = CONDITIONS[condition].perturbed
        per_clip = condition_rollouts(condition, rollouts_per_clip)  # a deterministic condition: one rollout says all
        clip_of = np.repeat(chosen, per_clip)  # the library's clip numbers: a clip's draws never depend on --clip
        rollout = np.tile(np.arange(per_clip), len(chosen))
        tasks = [EpisodeTask(int(starts[c]), max(1, int(ends[c] - starts[c]) - 1),
                             (int(seed), int(c), int(r)) if perturbed else None)
                 for c, r in zip(clip_of, rollout)]
        log.info("sim2sim whole clip, %s: %d clip(s) x %d rollout(s), %s control steps each, on %s, %d workers",
                 condition, len(chosen), per_clip, "/".join(str(t) for t in (ends - starts - 1)[chosen]), model_note,
                 workers)
        runs, wall_s[condition] = run_tasks(policy_path, mjm, spec, ref, tasks, workers, max_mpkpe_rel_mm,
                                            robust if perturbed else None)
        collected = collect(runs, layout.frame_to_bin.numpy()[starts[clip_of]], spec.num_frames)
        episodes = episode_table(collected.episodes, layout, ref, spec.control_dt_s, iteration)
        rows = rollout_table(episodes, collected.episodes, condition, clip_of, names, starts, ends, spec.fps)
        tables["rollouts"].append(rows)
        tables["bins"].append(bin_table(collected, episodes, layout, ref.segments).assign(condition=condition))
        tables["segments"].append(segment_table(collected, episodes, ref).assign(condition=condition))
        per_condition[condition] = {**condition_summary(rows), "rollouts_per_clip": per_clip,
                                    "eval_wall_time_s": wall_s[condition],
                                    "control_steps": int(rows["steps"].sum())}
    rollouts = pd.concat(tables["rollouts"], ignore_index=True)
    bins, segments = (_condition_first(pd.concat(tables[k], ignore_index=True)) for k in ("bins", "segments"))
    warp = warp_whole_clip(run_dir, label, spec.iteration, spec)
    gap = gap_table(rollouts, warp)
    for condition, s in per_condition.items():
        w = warp.get(condition)
        if w is not None:
            ours = w.clips[w.clips["clip"].isin(chosen)]  # the same clips (all of them without --clip)
            total, done = int(ours["rollouts"].sum()), int(ours["completed"].sum())
            s.update(warp_source=w.source, warp_rollouts=total, warp_success_rate=done / total,
                     success_gap=s["success_rate"] - done / total)
    summary = {
        "label": label, ITERATION: iteration, "checkpoint": str(policy_path), "run_dir": str(run_dir) if run_dir else "",
        "model": model, "model_description": model_note, "joint_dynamics": joint_dynamics, "workers": int(workers),
        "seed": int(seed), "rollouts_per_clip": int(rollouts_per_clip), "max_mpkpe_rel_mm": max_mpkpe_rel_mm,
        "start_transient_s": START_TRANSIENT_S, "clips": [names[c] for c in chosen],
        "clip_duration_s": durations_s[chosen].tolist(),
        "conditions": per_condition,
        **({"robust_perturbations": {"applied": robust.applied, "skipped": robust.skipped, "source": robust.source}}
           if robust is not None else {}),
    }
    return WholeClipResult(rollouts, bins, segments, survival_table(rollouts, durations_s), summary, gap)


def _condition_first(table: pd.DataFrame) -> pd.DataFrame:
    return table[["condition", *[c for c in table.columns if c != "condition"]]]


def format_whole_clip(result: WholeClipResult) -> str:
    """What the command prints: per condition, success, failures (start transients, later), where, survival."""
    s = result.summary
    lines = [f"sim2sim whole clip ({s['model_description']}): {len(s['clips'])} clip(s), "
             f"{', '.join(f'{n} {d:.1f} s' for n, d in zip(s['clips'], s['clip_duration_s']))}"]
    for condition, c in s["conditions"].items():
        failed = result.rollouts[(result.rollouts["condition"] == condition) & result.rollouts["failed"]]
        by_bin = failed.groupby("failure_bin")["failure_time_s"].agg(["size", "median"]).sort_values("size", ascending=False)
        where = ", ".join(f"{int(n)} in bin {b} (median {t:.1f} s)" for b, (n, t) in by_bin.head(5).iterrows())
        where += f", {len(by_bin) - 5} more bins" if len(by_bin) > 5 else ""
        lines.append(f"  {condition:8s} {c['completed']} of {c['rollouts']} rollouts completed the clip "
                     f"(success {c['success_rate']:.3f}); failures: {c['transient_failures']} start transient(s) "
                     f"(< {START_TRANSIENT_S:g} s), {c['later_failures']} later{': ' + where if where else ''}; "
                     f"mean survival {c['mean_survival_s']:.1f} s; {c['control_steps']} control steps in "
                     f"{c['eval_wall_time_s']:.0f} s")
        if not CONDITIONS[condition].perturbed and c["rollouts_per_clip"] == 1 and s["rollouts_per_clip"] > 1:
            lines.append("           (one nominal rollout per clip: native MuJoCo repeats it exactly)")
        if "warp_source" in c:
            lines.append(f"           bmimic (MuJoCo-Warp) {c['warp_success_rate']:.3f} over {c['warp_rollouts']} "
                         f"rollout(s), gap {c['success_gap']:+.3f}: {c['warp_source']}")
        else:
            lines.append("           bmimic (MuJoCo-Warp): no whole-clip evaluation of this checkpoint under this "
                         "condition in the run folder")
    if "robust_perturbations" in s:
        p = s["robust_perturbations"]
        lines.append(f"  robust perturbations: {', '.join(p['applied']) or 'none'} (from {p['source']})"
                     + (f"; not applied (no native version): {', '.join(p['skipped'])}" if p["skipped"] else ""))
    return "\n".join(lines)


__all__ = ["WholeClipResult", "check_rollouts", "clip_spans", "condition_summary", "format_whole_clip",
           "parse_conditions", "robust_perturbations", "rollout_table", "run_whole_clip", "run_config_section",
           "survival_table"]
