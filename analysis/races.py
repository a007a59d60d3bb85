"""``python -m analysis.races JSON [JSON ...] --out DIR``: the learning curves of ``bmimic.race`` runs,
side by side, against wall time from launch and against iterations.

A race JSON (``bmimic-race-1``, written by ``python -m bmimic.race --json``) holds every evaluation
of one race. This module reads several into tidy tables and draws them together, which is how a
change is judged against its baseline (issue 33: the change's learning curve beside the baseline's):

- ``read_races``: the JSONs, each read and checked once;
- ``race_evaluations``: one row per evaluation (race, config, seed, gpu, GPUs, envs per GPU and in all,
  date, iteration, env steps, wall time from launch, success rate, root-relative MPKPE);
- ``race_thresholds``: one row per race and threshold (reached or censored, when);
- ``race_summary`` / ``summary_markdown``: one row per race (start-up, seconds per iteration,
  evaluation share, each threshold's time and iteration): the race tables of docs/benchmarks.md;
- ``whole_clip_markdown``: the races judged on the whole clip, with env steps to each whole-clip threshold
  and to 99% window success and their final policy's whole-clip success with Wilson's interval over its
  rollouts (issue 44's whole-clip table);
- ``plot_races``: failure (1 - success, log scale, so 99% success is visible) and MPKPE against wall
  time from launch, iterations and env steps (all ranks' together: the axis on which 1 x 8192, 2 x 4096
  and 4 x 2048 envs compare); one colour per config and GPU count, one line style per seed.

A race under torchrun (``gpus`` > 1 in its JSON) is one race over its ranks: ``num_envs`` is per GPU;
a JSON without ``gpus`` (a single process, and every race before torchrun races) is one GPU. Wall time
is only comparable between races on the same card kind under the same load; the GPU name (with the
GPU count when more than one) is part of every label for that reason.
"""

from bmimic.cli.startup import leave_working_directory

leave_working_directory(__spec__.name)  # first: under `python -m` (bmimic.cli.startup); no MuJoCo here

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from analysis import REFUSED, AnalysisError, error_line
from analysis.binomial import wilson_interval
from analysis.files import save_figure, write_csv, write_text
from analysis.markdown import is_nan, md_table
from analysis.palette import arm_colors
from analysis.race_files import EVALUATION_KEYS, THRESHOLD_KEYS, read_race
from bmimic.cli.common import path_arg
from bmimic.runs.atomic_io import staged_folder
from bmimic.runs.race_record import WHOLE_CLIP_METRIC
from bmimic.runs.schema import ENV_STEPS, ITERATION, MPKPE_REL_MM, SUCCESS_RATE

LABEL_IGNORED = ("seed", "hydra.", "logger", "progress_bar", "motion", "eval.", "run_name")
"""Overrides that do not name the trained config (its seed, where it logs, how it is evaluated)."""

SUCCESS_TARGET = 0.99
"""Success the race's headline asks for (drawn as a line on the failure panels)."""

LINESTYLES = ("-", "--", ":", "-.")
"""Line style per seed (cycles past four seeds)."""


def config_label(config: dict) -> str:
    """What was trained, from a race's config: env, sampler, env count, then any other training override
    (seed, logging, motion and evaluation settings left out)."""
    overrides = [str(o) for o in config.get("overrides") or []]
    # config["env"]: the env group the race trained (recorded since 2026-11-29); before, an override named it
    # or the default (beyondmimic) ran.
    env = config.get("env") or next((o.split("=", 1)[1] for o in overrides if o.startswith("env=")), "beyondmimic")
    parts = [f"env={env}", f"sampler={config.get('sampler', '?')}", f"num_envs={config.get('num_envs', '?')}"]
    named = ("env=", "sampler=", "num_envs=")
    parts += [o for o in overrides if not o.startswith(named) and not o.lstrip("+~").startswith(LABEL_IGNORED)]
    return " ".join(parts)


def read_races(paths) -> list[tuple[str, dict]]:
    """Every race JSON of ``paths``, read and checked once, with its name (the file's stem), in order."""
    return [(Path(p).stem, read_race(p)) for p in paths]


def _identity(name: str, data: dict) -> dict:
    """The columns that say which race a row belongs to: its name, what was trained, seed, GPU kind,
    GPUs (ranks), envs per GPU and in all, date and evaluation cadence."""
    cfg, machine = data["config"], data.get("machine") or {}
    gpu = (machine.get("gpu") or {}).get("name") or "cpu"
    gpus = int(data.get("gpus") or 1)
    per_gpu = data.get("num_envs_per_gpu", cfg.get("num_envs"))
    return {"race": name, "config": config_label(cfg), "seed": cfg.get("seed"),
            "gpu": str(gpu).replace("NVIDIA ", "").split(" ")[0], "gpus": gpus, "num_envs_per_gpu": per_gpu,
            "num_envs_total": per_gpu * gpus if isinstance(per_gpu, int) else None,
            "date": str(machine.get("created") or "")[:10], "eval_every_iters": (cfg.get("eval") or {}).get("every_iters")}


IDENTITY = ["race", "config", "seed", "gpu", "gpus", "num_envs_per_gpu", "num_envs_total", "date", "eval_every_iters"]
"""_identity's columns, first in every table."""


def gpu_label(gpu: pd.Series, gpus: pd.Series) -> pd.Series:
    """`H200` for one GPU, `4 x H200` for a race over four (tables and legends)."""
    return pd.Series([g if n == 1 else f"{n} x {g}" for g, n in zip(gpu, gpus)], index=gpu.index, dtype=object)


def race_evaluations(races: list[tuple[str, dict]]) -> pd.DataFrame:
    """Every evaluation of every race (``read_races``), one row each (tidy; see the module docstring)."""
    rows = [{**_identity(name, data), **{k: e[k] for k in EVALUATION_KEYS}}
            for name, data in races for e in data["evaluations"]]
    return pd.DataFrame(rows, columns=[*IDENTITY, *EVALUATION_KEYS])


def race_thresholds(races: list[tuple[str, dict]]) -> pd.DataFrame:
    """Each race's thresholds: metric, value, reached or censored, and when (iteration, env steps, wall
    time from launch and from the first iteration; empty when censored)."""
    rows = [{**_identity(name, data), **{k: t.get(k) for k in THRESHOLD_KEYS}}
            for name, data in races for t in data.get("thresholds") or []]
    df = pd.DataFrame(rows, columns=[*IDENTITY, *THRESHOLD_KEYS])
    return df.astype({ITERATION: "Int64", ENV_STEPS: "Int64"})  # censored rows stay empty, the rest integers


def _threshold_name(metric: str, value: float) -> str:
    if metric == WHOLE_CLIP_METRIC:
        return f"{value:.0%} robust whole-clip success"
    return f"{value:.0%} success" if metric == "eval_success_rate" else f"MPKPE <= {value:g} mm"


def _steps(x) -> str:
    """Env steps as `1.97e8`."""
    mantissa, exponent = f"{float(x):.2e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def _cell(t: dict, censored_at: float, steps: bool = False) -> str:
    """`440 s (it 1600)` for a reached threshold (`steps`: `440 s (it 1600, 1.57e8)`), `> 538 s` for a censored
    one (not by the race's end)."""
    if t.get("status") == "reached":
        return f"{t['wall_from_launch_s']:.0f} s (it {t[ITERATION]}" + (f", {_steps(t[ENV_STEPS])})" if steps else ")")
    return f"> {censored_at:.0f} s" if np.isfinite(censored_at) else "–"


def race_summary(races: list[tuple[str, dict]]) -> pd.DataFrame:
    """One row per race (``read_races``): what was raced, start-up (launch to the first iteration),
    training seconds per iteration (training time over iterations at the last evaluation), the
    evaluations' share of the wall time after start-up, why it stopped, and one column per threshold:
    wall time from launch with the iteration, or `> T s` when the race ended at T without it. The table
    docs/benchmarks.md quotes."""
    rows = []
    for name, data in races:
        last = data["evaluations"][-1] if data["evaluations"] else {}
        wall = last.get("wall_from_launch_s")
        end = float(wall) if wall is not None else math.nan
        per_it = (float(last["training_s"]) / last[ITERATION]
                  if last.get("training_s") is not None and last.get(ITERATION) else math.nan)
        row = {**_identity(name, data), "startup_s": data.get("startup_s"), "training_s_per_iteration": per_it,
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
    thresholds = [c for c in summary.columns if c.endswith("% success") or c.startswith("MPKPE <=")
                  or c.endswith("whole-clip success")]
    view = summary[fixed + thresholds + ["last_success"]].copy()
    view["gpu"] = gpu_label(summary["gpu"], summary["gpus"])
    formats = {"startup_s": "{:.0f} s", "training_s_per_iteration": "{:.3f}", "eval_share": "{:.1%}",
               "last_success": "{:.3f}"}
    for col, form in formats.items():
        view[col] = view[col].map(lambda x, form=form: "–" if is_nan(x) else form.format(x))
    view = view.rename(columns={"eval_every_iters": "eval every", "startup_s": "start-up",
                                "training_s_per_iteration": "training s/iteration", "eval_share": "evaluation share",
                                "last_success": "success at the end"})
    return md_table(view)


CURVE_AXES = (("wall_from_launch_s", "wall time from launch [s]"), (ITERATION, "iteration"),
              (ENV_STEPS, "env steps (all GPUs)"))
"""The x axes of the race curves, one column of panels each."""


FINAL_WHOLE_CLIP = "final policy, robust whole clip [95% Wilson interval over its rollouts]"
"""The whole-clip table's last column: one judgement of R rollouts pins the policy's success down only to
about ±0.04 at 0.95 with R = 128, the width that decides whether a 95% line is held twice in a row."""


def _whole_clip_rollouts(data: dict) -> int | None:
    """How many rollouts each whole-clip judgement of a race ran (its config's eval.whole_clip.rollouts)."""
    rollouts = ((data["config"].get("eval") or {}).get("whole_clip") or {}).get("rollouts")
    return int(rollouts) if isinstance(rollouts, int | float) and rollouts >= 1 else None


def _wilson_text(success: float, rollouts: int | None) -> str:
    """`` [low, high]`` of a success read from ``rollouts`` rollouts, or nothing when their number is unknown."""
    if rollouts is None:
        return ""
    low, high = wilson_interval(round(success * rollouts), rollouts)
    return f" [{low:.3f}, {high:.3f}]"


def whole_clip_markdown(races: list[tuple[str, dict]]) -> str | None:
    """The races judged on the whole clip (a robust whole-clip threshold in their JSON), one row each: GPUs and
    envs per GPU, seed, start-up, wall time from launch, iteration and env steps to each whole-clip threshold
    and to 99% window success (`> T s` when the race ended at T without it), and the final policy's robust
    whole-clip success with its judge (native MuJoCo or MuJoCo-Warp) and, where the race recorded its number
    of rollouts, Wilson's 95% interval over them. None when no race has a whole-clip line."""
    rows = []
    for name, data in races:
        ts = data.get("thresholds") or []
        whole = [t for t in ts if t.get("metric") == WHOLE_CLIP_METRIC]
        if not whole:
            continue
        last = data["evaluations"][-1] if data["evaluations"] else {}
        end = float(last.get("wall_from_launch_s", math.nan))
        ident = _identity(name, data)
        row = {"config": ident["config"], "gpu": ident["gpu"], "gpus": ident["gpus"],
               "envs per GPU": ident["num_envs_per_gpu"], "seed": ident["seed"], "date": ident["date"],
               "start-up": "–" if data.get("startup_s") is None else f"{data['startup_s']:.0f} s"}
        for t in sorted(whole, key=lambda t: float(t["threshold"])):
            row[_threshold_name(WHOLE_CLIP_METRIC, float(t["threshold"]))] = _cell(t, end, steps=True)
        window = [t for t in ts if t.get("metric") == "eval_success_rate" and float(t["threshold"]) == SUCCESS_TARGET]
        row[f"{SUCCESS_TARGET:.0%} window success"] = _cell(window[0], end, steps=True) if window else "–"
        final = data.get("final_whole_clip") or {}
        value = final.get(WHOLE_CLIP_METRIC)
        row[FINAL_WHOLE_CLIP] = "–" if value is None else (
            f"{value:.3f}{_wilson_text(value, _whole_clip_rollouts(data))} "
            f"({'native MuJoCo' if final.get('native') else 'MuJoCo-Warp'}, it {final.get(ITERATION)})")
        rows.append(row)
    if not rows:
        return None
    table = pd.DataFrame(rows).fillna("–")
    table.insert(1, "GPUs", gpu_label(table.pop("gpu"), table.pop("gpus")))
    return md_table(table)


def plot_races(evals: pd.DataFrame, figsize=(15.0, 7.0)) -> Figure:
    """Six panels: failure (log, top) and MPKPE (bottom) against wall time from launch, iterations and
    env steps (CURVE_AXES). One line per race: colour by config, GPU kind and count, date and evaluation
    cadence, style by seed."""
    if evals.empty:
        raise AnalysisError("no evaluations to draw (every race JSON has an empty 'evaluations' list)")
    fig = Figure(figsize=figsize, layout="constrained")
    axes = fig.subplots(2, len(CURVE_AXES), sharey="row")
    # (each part as text, a missing one as "?": pandas' string columns keep None as missing, and a key that is
    # missing has no colour)
    every = ["?" if v is None or v != v else str(v) for v in evals["eval_every_iters"]]
    keys = np.array([f"{c} ({g}, {d}, eval every {e})" for c, g, d, e in
                     zip(evals["config"], gpu_label(evals["gpu"], evals["gpus"]), evals["date"], every)], dtype=object)
    colors = arm_colors(keys)
    seeds = sorted(evals["seed"].dropna().unique().tolist())
    floor = 1e-3  # failure 0 drawn at the floor: a log axis has no zero
    for _, df in evals.assign(key=keys).groupby("race", sort=True):
        df = df.sort_values(ITERATION)
        key, seed = df["key"].iloc[0], df["seed"].iloc[0]
        style = LINESTYLES[seeds.index(seed) % len(LINESTYLES)] if seed in seeds else "-"
        failure = np.maximum(1.0 - df[SUCCESS_RATE].to_numpy(float), floor)
        for col, (x, _) in enumerate(CURVE_AXES):
            kw = {"color": colors[key], "ls": style, "lw": 1.3, "marker": "o", "ms": 2.5}
            axes[0, col].plot(df[x], failure, label=f"{key} seed {seed}" if col == 0 else None, **kw)
            axes[1, col].plot(df[x], df[MPKPE_REL_MM], **kw)
    for col, (_, xlabel) in enumerate(CURVE_AXES):
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
    """Write ``race_evaluations.csv``, ``race_thresholds.csv``, ``race_summary.csv``, ``race_table.md``,
    ``whole_clip_table.md`` (when a race was judged on the whole clip) and ``race_curves.png`` into ``out`` (every input is read and checked before anything is written)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise AnalysisError(f"--out {out}: is a file, not a folder")
    races = read_races(paths)
    evals, thresholds, summary = race_evaluations(races), race_thresholds(races), race_summary(races)
    fig, whole = plot_races(evals), whole_clip_markdown(races)
    with staged_folder(out) as stage:  # a write that fails (a full disk) leaves `out` as it was
        written = [write_csv(stage / "race_evaluations.csv", evals), write_csv(stage / "race_thresholds.csv", thresholds),
                   write_csv(stage / "race_summary.csv", summary),
                   write_text(stage / "race_table.md", summary_markdown(summary)),
                   *([] if whole is None else [write_text(stage / "whole_clip_table.md", whole)]),
                   save_figure(stage / "race_curves.png", fig)]
    return [out / p.name for p in written]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m analysis.races", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=path_arg, help="race JSONs (python -m bmimic.race --json)")
    parser.add_argument("--out", type=path_arg, required=True, help="folder for the CSVs and race_curves.png")
    args = parser.parse_args(argv)
    try:
        written = write_race_curves(args.paths, args.out)
    except REFUSED as e:
        print(error_line(e), file=sys.stderr)
        return 2
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
