"""``python -m analysis.races JSON [JSON ...] --out DIR``: the learning curves of ``bmimic.race`` runs,
side by side, against wall time from launch and against iterations.

A race JSON (``bmimic-race-1``, written by ``python -m bmimic.race --json``) holds every evaluation
of one race. This module reads several into tidy tables and draws them together, which is how a
change is judged against its baseline (issue 33: the change's learning curve beside the baseline's):

- ``race_evaluations``: one row per evaluation (race, config, seed, gpu, date, iteration, env steps, wall
  time from launch, success rate, root-relative MPKPE);
- ``race_thresholds``: one row per race and threshold (reached or censored, when);
- ``race_summary`` / ``summary_markdown``: one row per race (start-up, seconds per iteration,
  evaluation share, each threshold's time and iteration): the race tables of docs/benchmarks.md;
- ``plot_races``: failure (1 - success, log scale, so 99% success is visible) and MPKPE against wall
  time from launch and against iterations; one colour per config, one line style per seed.

Wall time is only comparable between races on the same card kind under the same load; the GPU name
is part of every label for that reason.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from analysis import AnalysisError
from analysis.files import save_figure, write_csv, write_text
from analysis.markdown import is_nan, md_table
from analysis.plots import arm_colors
from bmimic import BmimicError
from bmimic.run_schema import ENV_STEPS, ITERATION, MPKPE_REL_MM, RACE_KIND, SUCCESS_RATE

EVALUATION_KEYS = (ITERATION, ENV_STEPS, "wall_from_launch_s", SUCCESS_RATE, MPKPE_REL_MM)
"""Keys every evaluation record of a race JSON must have."""

LABEL_IGNORED = ("seed", "hydra.", "logger", "progress_bar", "motion", "eval.", "run_name")
"""Overrides that do not name the trained config (its seed, where it logs, how it is evaluated)."""

SUCCESS_TARGET = 0.99
"""Success the race's headline asks for (drawn as a line on the failure panels)."""

LINESTYLES = ("-", "--", ":", "-.")
"""Line style per seed (cycles past four seeds)."""


def read_race(path: str | Path) -> dict:
    """One race JSON, checked: its kind, its config and every evaluation's keys (AnalysisError, one line
    naming the file, otherwise)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise AnalysisError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise AnalysisError(f"{path}: not a readable JSON file ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict) or data.get("kind") != RACE_KIND:
        kind = data.get("kind") if isinstance(data, dict) else type(data).__name__
        raise AnalysisError(f"{path}: kind is {kind!r}, expected {RACE_KIND!r} (a bmimic.race --json file)")
    if not isinstance(data.get("config"), dict):
        raise AnalysisError(f"{path}: no 'config' object")
    evals = data.get("evaluations")
    if not isinstance(evals, list):
        raise AnalysisError(f"{path}: 'evaluations' is not a list")
    for i, e in enumerate(evals):
        missing = [k for k in EVALUATION_KEYS if not isinstance(e, dict) or k not in e]
        if missing:
            raise AnalysisError(f"{path}: evaluation {i} lacks {', '.join(missing)}")
    return data


def config_label(config: dict) -> str:
    """What was trained, from a race's config: env, sampler, env count, then any other training override
    (seed, logging, motion and evaluation settings left out)."""
    overrides = [str(o) for o in config.get("overrides") or []]
    env = next((o.split("=", 1)[1] for o in overrides if o.startswith("env=")), "beyondmimic")
    parts = [f"env={env}", f"sampler={config.get('sampler', '?')}", f"num_envs={config.get('num_envs', '?')}"]
    named = ("env=", "sampler=", "num_envs=")
    parts += [o for o in overrides if not o.startswith(named) and not o.lstrip("+~").startswith(LABEL_IGNORED)]
    return " ".join(parts)


def _gpu(data: dict) -> str:
    gpu = ((data.get("machine") or {}).get("gpu") or {}).get("name") or "cpu"
    return str(gpu).replace("NVIDIA ", "").split(" ")[0]


def _date(data: dict) -> str:
    return str((data.get("machine") or {}).get("created") or "")[:10]


def race_evaluations(paths) -> pd.DataFrame:
    """Every evaluation of every race in ``paths``, one row each (tidy; see the module docstring)."""
    rows = []
    for path in paths:
        data = read_race(path)
        cfg = data["config"]
        label, seed, gpu, date = config_label(cfg), cfg.get("seed"), _gpu(data), _date(data)
        for e in data["evaluations"]:
            rows.append({"race": Path(path).stem, "config": label, "seed": seed, "gpu": gpu, "date": date,
                         "eval_every_iters": (cfg.get("eval") or {}).get("every_iters"),
                         **{k: e[k] for k in EVALUATION_KEYS}})
    cols = ["race", "config", "seed", "gpu", "date", "eval_every_iters", *EVALUATION_KEYS]
    return pd.DataFrame(rows, columns=cols)


def race_thresholds(paths) -> pd.DataFrame:
    """Each race's thresholds: metric, value, reached or censored, and when (iteration, env steps, wall
    time from launch and from the first iteration; empty when censored)."""
    rows = []
    for path in paths:
        data = read_race(path)
        cfg = data["config"]
        for t in data.get("thresholds") or []:
            rows.append({"race": Path(path).stem, "config": config_label(cfg), "seed": cfg.get("seed"),
                         "gpu": _gpu(data), "metric": t.get("metric"), "threshold": t.get("threshold"),
                         "status": t.get("status"), ITERATION: t.get(ITERATION), ENV_STEPS: t.get(ENV_STEPS),
                         "wall_from_launch_s": t.get("wall_from_launch_s"),
                         "wall_from_first_iteration_s": t.get("wall_from_first_iteration_s")})
    df = pd.DataFrame(rows, columns=["race", "config", "seed", "gpu", "metric", "threshold", "status", ITERATION,
                                     ENV_STEPS, "wall_from_launch_s", "wall_from_first_iteration_s"])
    return df.astype({ITERATION: "Int64", ENV_STEPS: "Int64"})  # censored rows stay empty, the rest integers


def _threshold_name(metric: str, value: float) -> str:
    return f"{value:.0%} success" if metric == "eval_success_rate" else f"MPKPE <= {value:g} mm"


def _cell(t: dict, censored_at: float) -> str:
    """`440 s (it 1600)` for a reached threshold, `> 538 s` for a censored one (not by the race's end)."""
    if t.get("status") == "reached":
        return f"{t['wall_from_launch_s']:.0f} s (it {t[ITERATION]})"
    return f"> {censored_at:.0f} s" if np.isfinite(censored_at) else "–"


def race_summary(paths) -> pd.DataFrame:
    """One row per race: what was raced, start-up (launch to the first iteration), training seconds per
    iteration (training time over iterations at the last evaluation), the evaluations' share of the
    wall time after start-up, why it stopped, and one column per threshold: wall time from launch with
    the iteration, or `> T s` when the race ended at T without it. The table docs/benchmarks.md quotes."""
    rows = []
    for path in paths:
        data = read_race(path)
        cfg, evals = data["config"], data["evaluations"]
        last = evals[-1] if evals else {}
        end = float(last.get("wall_from_launch_s", math.nan))
        per_it = (float(last["training_s"]) / last[ITERATION]
                  if last.get("training_s") is not None and last.get(ITERATION) else math.nan)
        row = {"race": Path(path).stem, "config": config_label(cfg), "seed": cfg.get("seed"), "gpu": _gpu(data),
               "date": _date(data), "eval_every_iters": (cfg.get("eval") or {}).get("every_iters"),
               "startup_s": data.get("startup_s"), "training_s_per_iteration": per_it,
               "eval_share": data.get("eval_overhead"), "last_iteration": last.get(ITERATION),
               "last_success": last.get(SUCCESS_RATE), "stopped": data.get("stopped")}
        for t in data.get("thresholds") or []:
            row[_threshold_name(t.get("metric"), float(t.get("threshold")))] = _cell(t, end)
        rows.append(row)
    return pd.DataFrame(rows)


def summary_markdown(summary: pd.DataFrame) -> str:
    """race_summary as the markdown table of docs/benchmarks.md (rounded, units in the headers)."""
    if summary.empty:
        return md_table(summary)
    fixed = ["config", "seed", "gpu", "date", "eval_every_iters", "startup_s", "training_s_per_iteration",
             "eval_share"]
    thresholds = [c for c in summary.columns if c.endswith("% success") or c.startswith("MPKPE <=")]
    view = summary[fixed + thresholds + ["last_success"]].copy()
    view["startup_s"] = view["startup_s"].map(lambda x: f"{x:.0f} s" if not is_nan(x) else "–")
    view["training_s_per_iteration"] = view["training_s_per_iteration"].map(
        lambda x: f"{x:.3f}" if not is_nan(x) else "–")
    view["eval_share"] = view["eval_share"].map(lambda x: f"{100 * x:.1f}%" if not is_nan(x) else "–")
    view["last_success"] = view["last_success"].map(lambda x: f"{x:.3f}" if not is_nan(x) else "–")
    view = view.rename(columns={"eval_every_iters": "eval every", "startup_s": "start-up", "training_s_per_iteration": "training s/iteration",
                                "eval_share": "evaluation share", "last_success": "success at the end"})
    return md_table(view)


def plot_races(evals: pd.DataFrame, figsize=(11.0, 7.0)) -> Figure:
    """Four panels: failure (log) and MPKPE against wall time from launch (left) and iterations (right).
    One line per race: colour by config, GPU, date and evaluation cadence, style by seed."""
    if evals.empty:
        raise AnalysisError("no evaluations to draw (every race JSON has an empty 'evaluations' list)")
    fig = Figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(2, 2, sharey="row")
    keys = (evals["config"] + " (" + evals["gpu"] + ", " + evals["date"] + ", eval every "
            + evals["eval_every_iters"].astype(str) + ")").to_numpy()
    colors = arm_colors(keys)
    seeds = sorted(evals["seed"].dropna().unique().tolist())
    floor = 1e-3  # failure 0 drawn at the floor: a log axis has no zero
    for _, df in evals.assign(key=keys).groupby("race", sort=True):
        df = df.sort_values(ITERATION)
        key, seed = df["key"].iloc[0], df["seed"].iloc[0]
        style = LINESTYLES[seeds.index(seed) % len(LINESTYLES)] if seed in seeds else "-"
        failure = np.maximum(1.0 - df[SUCCESS_RATE].to_numpy(float), floor)
        for col, x in enumerate(("wall_from_launch_s", ITERATION)):
            kw = {"color": colors[key], "ls": style, "lw": 1.3, "marker": "o", "ms": 2.5}
            axes[0, col].plot(df[x], failure, label=f"{key} seed {seed}" if col == 0 else None, **kw)
            axes[1, col].plot(df[x], df[MPKPE_REL_MM], **kw)
    for col, xlabel in enumerate(("wall time from launch [s]", "iteration")):
        axes[0, col].set_yscale("log")
        axes[0, col].axhline(1.0 - SUCCESS_TARGET, color="0.4", lw=0.8, ls="--")
        axes[1, col].set_xlabel(xlabel)
        for row in (0, 1):
            axes[row, col].grid(alpha=0.3)
    axes[0, 0].set_ylabel("evaluated failure (1 - success)")
    axes[1, 0].set_ylabel("root-relative MPKPE [mm]")
    fig.legend(loc="outside lower center", fontsize=7, ncols=2, frameon=False)
    return fig


def write_race_curves(paths, out: str | Path) -> list[Path]:
    """Write ``race_evaluations.csv``, ``race_thresholds.csv``, ``race_summary.csv``, ``race_table.md``
    and ``race_curves.png`` into ``out`` (every input is read and checked before anything is written)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise AnalysisError(f"--out {out}: is a file, not a folder")
    evals, thresholds, summary = race_evaluations(paths), race_thresholds(paths), race_summary(paths)
    fig = plot_races(evals)
    return [write_csv(out / "race_evaluations.csv", evals), write_csv(out / "race_thresholds.csv", thresholds),
            write_csv(out / "race_summary.csv", summary), write_text(out / "race_table.md", summary_markdown(summary)),
            save_figure(out / "race_curves.png", fig)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m analysis.races", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path, help="race JSONs (python -m bmimic.race --json)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the CSVs and race_curves.png")
    args = parser.parse_args(argv)
    try:
        written = write_race_curves(args.paths, args.out)
    except (AnalysisError, BmimicError) as e:  # BmimicError: a write the disk refuses (bmimic.atomic_io)
        print(f"error: {str(e).strip().splitlines()[0]}", file=sys.stderr)
        return 2
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
