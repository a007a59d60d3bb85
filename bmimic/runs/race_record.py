"""The race's bookkeeping (bmimic.race): its clock, which starts when the process does, its finish
lines (Threshold) and the stopping rule and record of one race (Race: every evaluation, when each
threshold was first held `sustain` evaluations in a row, the race.json record). Light: no torch, no
Hydra, so that bmimic.race reads the clock before any heavy import."""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from bmimic.runs.folder import portable_path
from bmimic.runs.schema import (
    ENV_STEPS,
    ITERATION,
    MPKPE_REL_MM,
    RACE_KIND,
    SUCCESS_RATE,
    summary_key,
    whole_clip_key,
)

if TYPE_CHECKING:
    from bmimic.runs.race_judge import NativeJudge


def _process_start_unix_s() -> float:
    """When this process started (Linux: /proc, 10 ms resolution); else now (this module's import)."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/stat") as f:
            boot = next(int(line.split()[1]) for line in f if line.startswith("btime "))
        return boot + start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, StopIteration):
        return time.time()


LAUNCH_UNIX_S = _process_start_unix_s()
"""The race's clock starts here, before any heavy import."""

WHOLE_CLIP_METRIC = whole_clip_key("robust", "success_rate")
"""The whole-clip finish line's measure: robust whole-clip success (bmimic.training.whole_clip)."""


@dataclass
class Threshold:
    """One finish line: `metric` (eval_success_rate, reached when >=; eval_mpkpe_rel_mm, when <=)."""

    metric: str
    value: float
    streak: int = 0
    """Evaluations in a row that met it, up to the latest."""
    reached_at: dict | None = None
    """The evaluation record where the sustained run began (None: not yet)."""
    first: dict | None = None
    """The evaluation record where the current streak began."""

    def met(self, summary: dict) -> bool:
        x = float(summary.get(self.metric, math.nan))
        return x >= self.value if self.metric.endswith("success_rate") else x <= self.value

    def observe(self, record: dict, summary: dict, sustain: int) -> None:
        """One evaluation (`record`, with `summary` its measures): a threshold not measured in it waits (whole
        clips run less often than windows); reached once met `sustain` evaluations in a row that measured it,
        timed at the first of them."""
        if self.metric not in summary:
            return
        self.streak = self.streak + 1 if self.met(summary) else 0
        self.first = (record if self.streak == 1 else self.first) if self.streak else None
        if self.reached_at is None and self.streak >= sustain:
            self.reached_at = self.first

    @property
    def label(self) -> str:
        if self.metric == "eval_success_rate":
            return f"success >= {self.value:g}"
        if self.metric == WHOLE_CLIP_METRIC:
            return f"robust whole-clip success >= {self.value:g}"
        return f"root-relative MPKPE <= {self.value:g} mm"


@dataclass
class Race:
    """The stopping rule and the record: `on_evaluation` is bmimic.train's stop_rule."""

    thresholds: list[Threshold]
    budget_s: float
    sustain: int = 2
    launch_unix_s: float = LAUNCH_UNIX_S
    evaluations: list[dict] = field(default_factory=list)
    stopped: str = "max_iterations"
    run_dir: str | None = None
    first_iteration_unix_s: float | None = None
    eval_time_s: float = 0.0
    rank_launch_unix_s: list[float] = field(default_factory=list)
    """Under torchrun: every rank's launch, in rank order (`launch_unix_s` is the earliest); else empty."""
    final_whole_clip: dict | None = None
    """The final policy's robust whole-clip evaluation (record_final), whether or not the clock saw it."""
    judge: NativeJudge | None = None
    """A bmimic.runs.race_judge.NativeJudge (--native-whole-clip): whole clips judged in native MuJoCo beside
    training, each result placed at its checkpoint's evaluation (None: MuJoCo-Warp's, in the evaluations)."""

    def join_ranks(self, launches: list[float]) -> None:
        """One race over the ranks whose launch times these are: the clock starts at the earliest."""
        self.rank_launch_unix_s = list(launches)
        self.launch_unix_s = min(launches)

    @property
    def gpus(self) -> int:
        """Ranks in the race (one GPU each under NCCL)."""
        return max(1, len(self.rank_launch_unix_s))

    def on_evaluation(self, trainer, summary: dict, now: float | None = None) -> bool:
        """Record this evaluation; True once every threshold is reached or the budget is spent."""
        now = time.time() if now is None else now
        self.run_dir = portable_path(trainer.run_dir)  # the record travels (docs/bench/): no machine paths
        self.first_iteration_unix_s = trainer.learn_started_unix_s
        self.eval_time_s = float(trainer.eval_time_s)
        p = trainer.progress
        record = {
            ITERATION: int(p.iteration), ENV_STEPS: int(p.env_steps),
            "wall_from_launch_s": now - self.launch_unix_s,
            "wall_from_first_iteration_s": now - (self.first_iteration_unix_s or self.launch_unix_s),
            "training_s": float(p.wall_time_s), "evaluation_s": self.eval_time_s,
            SUCCESS_RATE: float(summary.get("eval_success_rate", math.nan)),
            MPKPE_REL_MM: float(summary.get(summary_key(MPKPE_REL_MM), math.nan)),
        }
        if WHOLE_CLIP_METRIC in summary:
            record[WHOLE_CLIP_METRIC] = float(summary[WHOLE_CLIP_METRIC])
        self.evaluations.append(record)
        for t in self.thresholds:
            t.observe(record, summary, self.sustain)
        if self.judge is not None:
            for it, value in self.judge.poll(trainer.run_dir, record[SUCCESS_RATE]):
                self.judged(it, value)
        if all(t.reached_at is not None for t in self.thresholds):
            self.stopped = "every threshold reached"
            return True
        if record["wall_from_launch_s"] >= self.budget_s:
            self.stopped = f"wall budget of {self.budget_s:g} s from launch"
            return True
        return False

    def judged(self, iteration: int, value: float) -> None:
        """A native whole-clip result of the checkpoint of `iteration`: kept in that iteration's evaluation
        record (`whole_clip_native`) and observed by the whole-clip thresholds there, in checkpoint order."""
        record = next((e for e in reversed(self.evaluations) if e[ITERATION] == iteration), None)
        if record is None:  # the launch checks that checkpoints fall on evaluations; a stray one is no result
            return
        record.update({WHOLE_CLIP_METRIC: float(value), "whole_clip_native": True})
        for t in self.thresholds:
            if t.metric == WHOLE_CLIP_METRIC:
                t.observe(record, {WHOLE_CLIP_METRIC: float(value)}, self.sustain)

    def record_final(self, metrics: dict) -> None:
        """Keep the final policy's robust whole-clip result from the run's metrics.json (`final_whole_clip_*`,
        eval.whole_clip.at_end): `in_clock` when the race's last evaluation had measured it already."""
        final = {k.removeprefix("final_"): v for k, v in metrics.items() if k.startswith("final_whole_clip_robust_")}
        if WHOLE_CLIP_METRIC not in final:
            return
        last = self.evaluations[-1] if self.evaluations else {}
        it = int(metrics.get("iterations", -1))
        self.final_whole_clip = {
            ITERATION: it, ENV_STEPS: metrics.get(ENV_STEPS),
            WHOLE_CLIP_METRIC: float(final[WHOLE_CLIP_METRIC]),
            **{k: final[k] for k in (whole_clip_key("robust", "completed"), whole_clip_key("robust", "rollouts"))
               if k in final},
            "in_clock": last.get(ITERATION) == it and WHOLE_CLIP_METRIC in last}

    def record_final_native(self, value: float | None, metrics: dict) -> None:
        """The final policy's robust whole-clip success in native MuJoCo (the judge's, after the clock)."""
        if value is None:
            return
        self.final_whole_clip = {ITERATION: int(metrics.get("iterations", -1)), ENV_STEPS: metrics.get(ENV_STEPS),
                                 WHOLE_CLIP_METRIC: float(value), "native": True, "in_clock": False}

    def lines(self) -> list[str]:
        """One line per threshold, then where the time went."""
        last = self.evaluations[-1] if self.evaluations else None
        out = []
        for t in self.thresholds:
            r = t.reached_at
            if r is not None:
                out.append(f"race: {t.label} at iteration {r[ITERATION]} ({r[ENV_STEPS]:.3g} env steps): "
                           f"{r['wall_from_launch_s']:.0f} s from launch, {r['wall_from_first_iteration_s']:.0f} s "
                           "from the first iteration")
            elif last is not None:
                out.append(f"race: {t.label} not reached by iteration {last[ITERATION]} "
                           f"({last['wall_from_launch_s']:.0f} s from launch; censored)")
            else:
                out.append(f"race: {t.label} not reached (no evaluation ran)")
        f = self.final_whole_clip
        if f is not None:
            done, n = f.get(whole_clip_key("robust", "completed")), f.get(whole_clip_key("robust", "rollouts"))
            out.append(f"race: the final policy (iteration {f[ITERATION]}): robust whole-clip success"
                       + (" in native MuJoCo " if f.get("native") else " ")
                       + f"{f[WHOLE_CLIP_METRIC]:.3g}" + (f" ({done} of {n} rollouts)" if n else "")
                       + ("" if f["in_clock"] else ", evaluated after the clock stopped"))
        summary = self.summary()
        if self.gpus > 1:
            out.append(f"race: one race over {self.gpus} ranks, launched within "
                       f"{max(self.rank_launch_unix_s) - self.launch_unix_s:.1f} s; the clock starts at the earliest")
        if summary["startup_s"] is not None:
            out.append(f"race: start-up {summary['startup_s']:.0f} s (launch to the first iteration); evaluations "
                       f"{summary['evaluation_s']:.0f} s, {100 * summary['eval_overhead']:.1f}% of the wall time "
                       f"after start-up; stopped: {self.stopped}")
        return out

    def summary(self) -> dict:
        last = self.evaluations[-1] if self.evaluations else {}
        after_start = last.get("wall_from_first_iteration_s", math.nan)
        return {
            "startup_s": (self.first_iteration_unix_s - self.launch_unix_s) if self.first_iteration_unix_s else None,
            "evaluation_s": self.eval_time_s,
            "eval_overhead": self.eval_time_s / after_start if after_start and after_start > 0 else math.nan,
            "wall_total_s": last.get("wall_from_launch_s", math.nan),
            "stopped": self.stopped,
        }

    def ranks(self, num_envs_per_gpu) -> dict:
        """Under torchrun: the race's GPUs (ranks), envs per GPU and in all, and the launches' spread."""
        if self.gpus == 1:
            return {}  # a single process's race.json is as it always was
        total = num_envs_per_gpu * self.gpus if isinstance(num_envs_per_gpu, int) else None
        return {"gpus": self.gpus, "num_envs_per_gpu": num_envs_per_gpu, "num_envs_total": total,
                "rank_launch_spread_s": max(self.rank_launch_unix_s) - self.launch_unix_s}

    def to_json(self, config: dict, provenance: dict | None) -> dict:
        return {
            "kind": RACE_KIND,
            "run_dir": self.run_dir,
            "sustain": self.sustain,
            "budget_s": self.budget_s,
            "config": config,
            "machine": provenance,
            **self.ranks(config.get("num_envs")),
            **self.summary(),
            "thresholds": threshold_entries(self.thresholds),
            "evaluations": self.evaluations,
            **({"final_whole_clip": self.final_whole_clip} if self.final_whole_clip is not None else {}),
        }


def threshold_entries(thresholds: list[Threshold]) -> list[dict]:
    """race.json's `thresholds`: each one's metric, value, status and, when reached, where and when."""
    return [{"metric": t.metric, "threshold": t.value, "status": "reached" if t.reached_at else "censored",
             **({k: t.reached_at[k] for k in (ITERATION, ENV_STEPS, "wall_from_launch_s", "wall_from_first_iteration_s")}
                if t.reached_at else {})} for t in thresholds]


RECORD_SUMMARY_KEYS = {SUCCESS_RATE: summary_key(SUCCESS_RATE), MPKPE_REL_MM: summary_key(MPKPE_REL_MM),
                       WHOLE_CLIP_METRIC: WHOLE_CLIP_METRIC}
"""An evaluation record's measures (race.json) under the evaluation summary's names the thresholds read."""


def rejudge(record: dict, measured: dict[int, float], source: str) -> dict:
    """The race `record` (race.json) with robust whole-clip success measured afterwards (`measured`:
    iteration -> success, e.g. from its checkpoints; each iteration must be one the race evaluated at) added
    to its evaluations, and its thresholds decided again by the race's own rule (Threshold.observe) on the
    race's clock. `source` says where the added values come from (`whole_clip_source`). What the race
    measured itself is kept; an added value replaces none of it."""
    evaluations = [dict(e) for e in record["evaluations"]]
    at = {e[ITERATION]: e for e in evaluations}
    missing = sorted(set(measured) - set(at))
    if missing:
        raise ValueError(f"iterations {', '.join(map(str, missing))} have no evaluation in the race's record "
                         "(checkpoints align with evaluations when ppo.save_interval is a multiple of eval.every_iters)")
    for it, value in measured.items():
        if WHOLE_CLIP_METRIC not in at[it]:  # the race's own measurement stands
            at[it].update({WHOLE_CLIP_METRIC: float(value), "whole_clip_after_the_race": True})
    thresholds = [Threshold(t["metric"], float(t["threshold"])) for t in record["thresholds"]]
    for e in sorted(evaluations, key=lambda e: e[ITERATION]):
        summary = {name: e[key] for key, name in RECORD_SUMMARY_KEYS.items() if e.get(key) is not None}
        for t in thresholds:
            t.observe(e, summary, int(record["sustain"]))
    return {**record, "evaluations": evaluations, "thresholds": threshold_entries(thresholds),
            "whole_clip_source": source}

