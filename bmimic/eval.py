"""`python -m bmimic.eval RUN_DIR_OR_CHECKPOINT [options] [key=value ...]`: evaluate a trained policy.

    python -m bmimic.eval outputs/runs/default/2026-01-01_12-00-00            # the run's latest.pt
    python -m bmimic.eval outputs/runs/default/<stamp>/checkpoints/model_500.pt --episodes-per-bin 8
    python -m bmimic.eval RUN --horizon-s 4 --device cuda:1 eval.max_envs=1024 env.episode_length_s=20

The run's composed config (RUN_DIR/.hydra/config.yaml) is reloaded and its `auto`/null values are
resolved for this machine exactly as training does; dotted `key=value` overrides are merged on top.
Robot, motion, time bins and the evaluation environment are rebuilt like training's
(`bmimic.train.build_evaluator`), the actor is rebuilt from the checkpoint, and the
sampler-independent evaluation runs with the deterministic policy: `episodes_per_bin` episodes
start at stratified frames of every bin and run for `horizon_s`; an episode that terminates before
then (or, with eval.max_mpkpe_rel_mm, tracks worse than that on average) is a failure, charged to the
bin where it happened (bmimic.training.evaluation). Tables go to RUN_DIR/eval/<checkpoint>/
(latest.pt is named after its iteration, model_<it>, so re-evaluating after more training never
overwrites an older result):

    eval_episodes.parquet  one row per episode (start, end and failure frame and bin, errors)
    eval_bins.parquet      one row per time bin: visits, failures, failure_rate, start counts, errors
    eval_segments.csv      one row per motion segment, counted like the bins (visits, failures there)
    eval_summary.json      overall numbers (keys as in metrics.json: eval_success_rate, eval_mpkpe_mm, ...)

Bad input (missing folder, no checkpoint, a checkpoint that does not match the run's config) prints
one `error: ...` line and exits with status 2.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import logging
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from bmimic import BmimicError
from bmimic.console import quiet_warp

log = logging.getLogger("bmimic.eval")

CHECKPOINT_DIR = "checkpoints"
LATEST = "latest.pt"
TABLES = ("eval_episodes.parquet", "eval_bins.parquet", "eval_segments.csv", "eval_summary.json")


class EvalError(BmimicError):
    """A run folder, checkpoint or override that cannot be evaluated (one-line message)."""


# --------------------------------------------------------------------------------------------- loading
def locate_run(path: str | Path) -> tuple[Path, Path]:
    """(run folder, checkpoint) for a run folder (its latest.pt) or a checkpoint file inside one."""
    p = Path(path).expanduser()
    if not p.exists():
        raise EvalError(f"{p}: no such run folder or checkpoint")
    run_dir = p if p.is_dir() else p.resolve().parent.parent
    if not (run_dir / ".hydra" / "config.yaml").exists():
        where = "" if p.is_dir() else f" (the folder two levels above checkpoint {p.name})"
        raise EvalError(f"{run_dir}: not a run folder{where}: no .hydra/config.yaml")
    if not p.is_dir():
        return run_dir.resolve(), p.resolve()
    checkpoint = p / CHECKPOINT_DIR / LATEST
    if not checkpoint.exists():
        found = sorted((p / CHECKPOINT_DIR).glob("model_*.pt")) if (p / CHECKPOINT_DIR).is_dir() else []
        if not found:
            raise EvalError(f"{p}: no checkpoint ({CHECKPOINT_DIR}/{LATEST} or model_<it>.pt) in this run folder")
        checkpoint = max(found, key=_iteration_of_name)
    return run_dir.resolve(), checkpoint.resolve()


def _iteration_of_name(path: Path) -> int:
    try:
        return int(path.stem.split("_", 1)[1])
    except (IndexError, ValueError):
        return -1


def load_run_config(run_dir: Path, overrides: Sequence[str] = ()):
    """The run's composed config under the TrainConfig schema, with dotted `key=value` overrides merged."""
    import yaml
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from bmimic.config import TrainConfig

    path = run_dir / ".hydra" / "config.yaml"
    try:
        cfg = OmegaConf.merge(OmegaConf.structured(TrainConfig), OmegaConf.load(path))
    except (OmegaConfBaseException, OSError, ValueError, yaml.YAMLError) as e:
        raise EvalError(f"{path}: cannot be read as a bmimic config: {first_line(e)}") from None
    OmegaConf.set_struct(cfg, True)  # an override of a key that does not exist is an error, as in Hydra
    for item in overrides:
        key, sep, _ = item.partition("=")
        if not sep or not key or key.startswith(("+", "~")):
            raise EvalError(f"override {item!r}: expected a dotted key=value (e.g. eval.horizon_s=3)")
        try:
            cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist([item]))
        except OmegaConfBaseException as e:
            raise EvalError(f"override {item!r}: {first_line(e)}") from None
    return cfg


def anchor_relative_paths(cfg, run_dir: Path) -> None:
    """Relative input paths (motion.path, robot.mjcf_path, data.lafan_dir) were relative to the directory
    training was started in; resolve them against it (from .hydra/hydra.yaml) when they do not exist from here."""
    from omegaconf import OmegaConf

    try:
        launch_dir = Path(OmegaConf.load(run_dir / ".hydra" / "hydra.yaml").hydra.runtime.cwd)
    except Exception:  # no hydra.yaml (a hand-made run folder): paths stay relative to here
        return
    for group, key in (("motion", "path"), ("robot", "mjcf_path"), ("data", "lafan_dir")):
        value = (cfg.get(group) or {}).get(key)
        if value and not Path(value).expanduser().is_absolute() and not Path(value).exists():
            if (launch_dir / value).exists():
                cfg[group][key] = str(launch_dir / value)


@dataclass
class LoadedRun:
    """A run's config resolved for this machine, with the robot, motion and bins rebuilt from it."""

    run_dir: Path
    """The run folder."""
    checkpoint: Path
    """The checkpoint file to evaluate."""
    cfg: object
    """The composed, runtime-resolved DictConfig (overrides applied)."""
    device: str
    """Torch device everything runs on."""
    mjm: object
    """The robot's host mujoco.MjModel."""
    robot: object
    """bmimic.robot.RobotInfo."""
    motion: object
    """bmimic.motion.Motion at the control rate."""
    layout: object
    """bmimic.sampling.bins.BinLayout of the motion."""


def load_run(path: str | Path, overrides: Sequence[str] = (), trust: bool = False) -> LoadedRun:
    """Locate the run, reload and resolve its config, rebuild robot, motion and bins like training.

    A run folder may come from someone else: a config whose terms import modules outside bmimic
    (`func: package.module:function`) is refused unless `trust` (--trust-checkpoint)."""
    from bmimic.config import foreign_term_modules, resolve_runtime
    from bmimic.runs import resolve_device
    from bmimic.train import build_task

    run_dir, checkpoint = locate_run(path)
    cfg = load_run_config(run_dir, overrides)
    foreign = foreign_term_modules(cfg.env)
    if foreign and not trust:
        raise EvalError(f"{run_dir}: its config imports {', '.join(foreign)} (code outside bmimic) for env terms; "
                        "pass --trust-checkpoint if you trust this run folder")
    anchor_relative_paths(cfg, run_dir)
    device = resolve_device(cfg.device)
    resolve_runtime(cfg, device)
    mjm, robot, motion, layout = build_task(cfg, device)
    return LoadedRun(run_dir, checkpoint, cfg, device, mjm, robot, motion, layout)


def load_checkpoint(path: Path, device: str, trust: bool = False) -> dict:
    """The checkpoint dict, read with torch.load(weights_only=True) (`trust`: --trust-checkpoint, for
    your own checkpoints of format 1); it must hold an rsl-rl actor."""
    from bmimic.runs import load_checkpoint_file

    return load_checkpoint_file(path, device, trust)


def build_policy(state: dict, env, ppo_cfg, device: str, checkpoint: Path | str = "checkpoint"):
    """The deterministic actor (rsl-rl MLPModel) built as the Trainer builds it, weights from `state`."""
    from rsl_rl.utils import resolve_class

    from bmimic.training.runner import rsl_rl_train_cfg

    train_cfg = rsl_rl_train_cfg(ppo_cfg, "eval")
    actor_class, actor_kwargs = resolve_class(train_cfg["actor"])
    actor = actor_class(env.get_observations(), train_cfg["obs_groups"], "actor", env.num_actions, **actor_kwargs)
    try:
        actor.load_state_dict(state["actor_state_dict"], strict=True)
    except RuntimeError as e:
        raise EvalError(
            f"{checkpoint}: its actor does not match this run's config (ppo.actor_hidden_dims="
            f"{list(ppo_cfg.actor_hidden_dims)}, {actor.obs_dim} policy observations, {env.num_actions} "
            f"actions): {_mismatch(e)}"
        ) from None
    return actor.to(device).eval()


def _mismatch(e: RuntimeError) -> str:
    """The first concrete line of a load_state_dict error (which parameter, which shapes)."""
    lines = [x.strip() for x in str(e).splitlines() if x.strip()]
    return lines[1] if len(lines) > 1 else (lines[0] if lines else type(e).__name__)


def checkpoint_label(checkpoint: Path, state: dict) -> str:
    """Folder name of a checkpoint's results: its stem; latest.pt is named after its iteration."""
    if checkpoint.name == LATEST and "iter" in state:
        return f"model_{int(state['iter'])}"
    return checkpoint.stem


# --------------------------------------------------------------------------------------------- tables
def segment_at(segments, t_s: np.ndarray) -> tuple[list[str], list[str]]:
    """(segment name, difficulty) covering each time ('' where no segment does)."""
    names, levels = [], []
    for t in np.asarray(t_s, dtype=float):
        hit = next((s for s in segments if s.start_s <= t < s.end_s), None)
        names.append(hit.name if hit else "")
        levels.append(hit.difficulty if hit else "")
    return names, levels


def episode_table(raw: pd.DataFrame, layout, motion, step_dt: float, iteration: int) -> pd.DataFrame:
    """One row per episode: where it started and ended, whether and where it failed, how long it lived,
    and its mean errors (raw: Rollouts.episodes of Evaluator.run_episodes or another evaluator;
    layout: the BinLayout it was run with)."""
    from bmimic.training.evaluation import ERROR_COLUMNS

    edges = layout.edges_s.cpu().numpy()
    start_s = raw["start_frame"].to_numpy() / motion.fps
    segment, difficulty = segment_at(motion.segments, start_s)
    bins = raw["bin"].to_numpy()
    failed = raw["failed"].to_numpy().astype(bool)
    failure_frame = raw["failure_frame"].to_numpy().astype(int)
    fail_bin = layout.frame_to_bin.cpu().numpy()[np.where(failed, failure_frame, 0)]
    return pd.DataFrame({
        "iteration": int(iteration),
        "episode": np.arange(len(raw)),
        "bin": bins.astype(int),
        "bin_start_s": edges[bins],
        "bin_end_s": edges[bins + 1],
        "segment": segment,
        "difficulty": difficulty,
        "start_frame": raw["start_frame"].to_numpy().astype(int),
        "start_s": start_s,
        "end_frame": raw["end_frame"].to_numpy().astype(int),
        "failed": failed,
        "success": ~failed,
        "terminated": raw["terminated"].to_numpy().astype(bool),
        "error_failed": raw["error_failed"].to_numpy().astype(bool),
        "failure_frame": failure_frame,
        "failure_bin": np.where(failed, fail_bin, -1),
        "horizon_truncated": raw["horizon_truncated"].to_numpy().astype(bool),
        "steps": raw["steps"].to_numpy().astype(int),
        "survival_s": raw["steps"].to_numpy() * step_dt,
        **{c: raw[c].to_numpy(dtype=float) for c in ERROR_COLUMNS},
    })


def _with_rates(table: pd.DataFrame, survival_s: np.ndarray) -> pd.DataFrame:
    """success_rate (1 - failure_rate) and `mean_survival_s` (of the episodes started in each row's group)."""
    table.insert(table.columns.get_loc("failure_rate") + 1, "success_rate", 1.0 - table["failure_rate"])
    table.insert(table.columns.get_loc("start_failures") + 1, "mean_survival_s", survival_s)
    return table


def bin_table(rollouts, episodes: pd.DataFrame, layout, segments) -> pd.DataFrame:
    """One row per time bin of `layout`: failures where they happened per visit (training's eval.parquet
    columns), the start-bin counts, and the mean survival of the episodes started in it."""
    from bmimic.training.evaluation import bin_table as labelled_bins

    per_bin = labelled_bins(rollouts, layout, segments)
    per_bin.insert(0, "iteration", int(episodes["iteration"].iloc[0]))
    survival = episodes.groupby("bin")["survival_s"].mean().reindex(per_bin["bin"]).to_numpy(dtype=float)
    return _with_rates(per_bin, survival)


def segment_table(rollouts, episodes: pd.DataFrame, motion) -> pd.DataFrame:
    """One row per stretch of the motion covered by one segment ('' = no segment), in time order, with
    the same per-visit accounting as the bins: visits, failures where they happened, start counts."""
    from bmimic.training.evaluation import aggregate

    names, levels = segment_at(motion.segments, np.arange(motion.num_frames) / motion.fps)
    names = np.asarray(names, dtype=object)
    stretch = np.r_[0, np.cumsum(names[1:] != names[:-1])]  # contiguous frames of one label
    per_seg = aggregate(rollouts.episodes, stretch, rollouts.frame_errors)
    ids = per_seg.pop("bin").to_numpy()
    first = np.searchsorted(stretch, ids)
    last = np.searchsorted(stretch, ids, side="right") - 1
    per_seg.insert(0, "segment", names[first])
    per_seg.insert(1, "difficulty", np.asarray(levels, dtype=object)[first])
    per_seg.insert(2, "start_s", first / motion.fps)
    per_seg.insert(3, "end_s", (last + 1) / motion.fps)
    started = stretch[episodes["start_frame"].to_numpy()]
    survival = episodes.groupby(started)["survival_s"].mean().reindex(ids).to_numpy(dtype=float)
    return _with_rates(per_seg, survival)


# --------------------------------------------------------------------------------------------- evaluation
@dataclass
class EvalResult:
    """What `evaluate` produced, and where it was written."""

    episodes: pd.DataFrame
    """One row per episode."""
    bins: pd.DataFrame
    """One row per time bin."""
    segments: pd.DataFrame
    """One row per motion segment."""
    summary: dict
    """Overall numbers and provenance (eval_summary.json)."""
    out_dir: Path | None = None
    """Folder the tables were written to (None until written)."""


def evaluate(run: LoadedRun, overrides: Sequence[str] = (), trust: bool = False) -> EvalResult:
    """Run the sampler-independent evaluation of `run.checkpoint` and build the tables."""
    from bmimic.runs import seed_everything
    from bmimic.train import build_evaluator
    from bmimic.training.evaluation import summarize

    cfg = run.cfg
    state = load_checkpoint(run.checkpoint, run.device, trust)
    seed_everything(cfg.seed)
    evaluator = build_evaluator(cfg, run.device, run.robot, run.motion, run.layout)
    env = evaluator.env
    policy = build_policy(state, env, cfg.ppo, run.device, run.checkpoint)
    iteration = int(state.get("iter", -1))
    log.info("evaluating %s (iteration %d) on %s: %d bins x %d episodes, horizon %g s, %d worlds",
             run.checkpoint, iteration, run.device, run.layout.num_bins, cfg.eval.episodes_per_bin,
             cfg.eval.horizon_s, env.num_envs)
    t0 = time.perf_counter()
    rollouts = evaluator.run_episodes(policy)
    wall = time.perf_counter() - t0
    episodes = episode_table(rollouts.episodes, run.layout, run.motion, env.step_dt, iteration)
    bins = bin_table(rollouts, episodes, run.layout, run.motion.segments)
    segments = segment_table(rollouts, episodes, run.motion)
    progress = state.get("progress") or {}
    summary = {
        **summarize(bins),
        "episodes": int(len(episodes)),
        "failures": int(episodes["failed"].sum()),
        "num_bins": int(run.layout.num_bins),
        "episodes_per_bin": int(cfg.eval.episodes_per_bin),
        "horizon_s": float(cfg.eval.horizon_s),
        "max_mpkpe_rel_mm": cfg.eval.max_mpkpe_rel_mm,
        "horizon_truncated_bins": int(bins["horizon_truncated"].sum()),
        "eval_worlds": int(env.num_envs),
        "eval_wall_time_s": wall,
        "checkpoint": str(run.checkpoint),
        "iteration": iteration,
        "env_steps": int(progress.get("env_steps", -1)),
        "run_dir": str(run.run_dir),
        "motion": str(cfg.motion.name),
        "motion_duration_s": float(run.motion.duration_s),
        "seed": int(cfg.seed),
        "device": run.device,
        "overrides": list(overrides),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "label": checkpoint_label(run.checkpoint, state),
    }
    return EvalResult(episodes, bins, segments, summary)


def write_tables(result: EvalResult, out_dir: Path) -> Path:
    """Write the four tables atomically; the summary last, so its presence means a complete set."""
    from bmimic.runs import atomic_write, atomic_write_json, atomic_write_parquet

    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_parquet(out_dir / "eval_episodes.parquet", result.episodes)
    atomic_write_parquet(out_dir / "eval_bins.parquet", result.bins)
    atomic_write(out_dir / "eval_segments.csv", lambda tmp: result.segments.to_csv(tmp, index=False))
    atomic_write_json(out_dir / "eval_summary.json", result.summary)
    result.out_dir = out_dir
    return out_dir


# --------------------------------------------------------------------------------------------- report
_SHOWN = {
    "visits": ("visits", "{:d}"),
    "failures": ("failures", "{:d}"),
    "success_rate": ("success", "{:.3f}"),
    "mpkpe_mm": ("MPKPE_mm", "{:.1f}"),
    "mpkpe_rel_mm": ("rel_MPKPE_mm", "{:.1f}"),
    "anchor_ori_err_rad": ("anchor_ori_rad", "{:.3f}"),
    "body_ori_err_rad": ("body_ori_rad", "{:.3f}"),
    "joint_pos_err_rad": ("joint_pos_rad", "{:.3f}"),
    "joint_vel_err_radps": ("joint_vel_radps", "{:.2f}"),
    "ee_pos_err_mm": ("ee_pos_mm", "{:.1f}"),
}
MAX_BINS_SHOWN = 30


def _format_rows(df: pd.DataFrame, label_cols: dict[str, str], titles: dict[str, str] | None = None) -> str:
    shown = pd.DataFrame({title: df[col].astype(str) for col, title in label_cols.items()})
    for col, (title, fmt) in _SHOWN.items():
        title = (titles or {}).get(col, title)
        shown[title] = [fmt.format(int(v) if fmt == "{:d}" else float(v)) for v in df[col]]
    return shown.to_string(index=False)


def format_report(result: EvalResult) -> str:
    """A readable summary: per segment, per bin (the worst ones for long motions), overall."""
    s = result.summary
    lines = [
        f"{s['checkpoint']} (iteration {s['iteration']}), {s['device']}: {s['num_bins']} bins x "
        f"{s['episodes_per_bin']} episodes, horizon {s['horizon_s']:g} s, deterministic policy",
        "",
    ]
    seg = result.segments.assign(
        segment=[n or "(none)" for n in result.segments["segment"]],
        span=[f"{a:.1f}-{b:.1f}" if math.isfinite(a) else "" for a, b in zip(result.segments["start_s"],
                                                                             result.segments["end_s"])],
    )
    lines += ["per segment:", _format_rows(seg, {"segment": "segment", "difficulty": "difficulty", "span": "t_s"}), ""]
    bins = result.bins.assign(span=[f"{a:.1f}-{b:.1f}" + ("*" if t else "") for a, b, t in zip(
        result.bins["bin_start_s"], result.bins["bin_end_s"], result.bins["horizon_truncated"])])
    title = "per bin:"
    if len(bins) > MAX_BINS_SHOWN:
        bins = bins.sort_values(["success_rate", "mpkpe_mm"], ascending=[True, False]).head(MAX_BINS_SHOWN // 3)
        title = f"worst {len(bins)} of {len(result.bins)} bins:"
    lines += [title, _format_rows(bins, {"bin": "bin", "span": "t_s", "segment": "segment"}), ""]
    overall = pd.DataFrame([{"visits": s["episodes"], "failures": s["failures"], "success_rate": s["eval_success_rate"],
                             **{c: s[f"eval_{c}"] for c in _SHOWN if f"eval_{c}" in s}}])
    lines += ["overall:", _format_rows(overall, {}, titles={"visits": "episodes"}),
              f"bins mastered (failure rate < 0.1; a horizon-truncated bin only when tracked through): "
              f"{s['eval_bins_mastered_frac']:.2f}",
              "failures are charged to the bin (segment) where they happened, per visit; "
              "* = horizon-truncated (its episodes reach the clip end before the horizon)"]
    if result.out_dir is not None:
        lines.append(f"tables: {result.out_dir}")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------- CLI
def first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean bad input (printed as one line, exit status 2)."""
    from bmimic.motion.motion import MotionDataError

    return (BmimicError, MotionDataError)


def flag_overrides(args: argparse.Namespace) -> list[str]:
    """The convenience flags as dotted overrides (applied after the positional ones, so they win)."""
    out = []
    if args.episodes_per_bin is not None:
        out.append(f"eval.episodes_per_bin={args.episodes_per_bin}")
    if args.horizon_s is not None:
        out.append(f"eval.horizon_s={args.horizon_s}")
    if args.num_envs is not None:
        out.append(f"eval.max_envs={args.num_envs}")
    if args.device is not None:
        out.append(f"device={args.device}")
    return out


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bmimic.eval",
        description="Sampler-independent evaluation of a trained policy (deterministic actions).",
        epilog="Tables: RUN_DIR/eval/<checkpoint>/{" + ",".join(TABLES) + "}",
    )
    p.add_argument("path", help="a run folder (evaluates checkpoints/latest.pt) or a checkpoint file in one")
    p.add_argument("overrides", nargs="*", help="dotted config overrides key=value, e.g. eval.horizon_s=3")
    p.add_argument("--episodes-per-bin", type=int, help="episodes started per time bin (eval.episodes_per_bin)")
    p.add_argument("--horizon-s", type=float, help="seconds an episode must survive (eval.horizon_s)")
    p.add_argument("--num-envs", type=int, help="most simultaneous evaluation worlds (eval.max_envs)")
    p.add_argument("--device", help="cpu, cuda, cuda:N or auto (default: the run's device setting)")
    p.add_argument("--out", type=Path, help="folder for the tables (default RUN_DIR/eval/<checkpoint>)")
    add_trust_flag(p)
    return p


def add_trust_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="unpickle a checkpoint that torch.load(weights_only=True) refuses; only for checkpoints "
                        "you wrote yourself (bmimic checkpoint format 1): a shared one could run code")


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    quiet_warp()
    overrides = [*args.overrides, *flag_overrides(args)]
    try:
        run = load_run(args.path, overrides, trust=args.trust_checkpoint)
        result = evaluate(run, overrides, trust=args.trust_checkpoint)
        out_dir = args.out if args.out is not None else run.run_dir / "eval" / result.summary["label"]
        write_tables(result, out_dir.resolve())
    except user_errors() as e:
        print(f"error: {first_line(e)}", file=sys.stderr)
        return 2
    print(format_report(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
