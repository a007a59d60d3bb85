"""The run record's contract: the columns of every run table, with units and labels, the metrics.json
keys, the mastery rule, the logistics keys and the budget keys. Producers (training, `bmimic.eval`,
sim2sim) and readers (evaluation's report, the analysis) spell these names through this module only.

File names are `bmimic.runs.folder`'s; this module says what the files hold. It is torch-free and imports
nothing heavy (the analysis imports it without torch; sim2sim, numpy only, imports it too).
A test (tests/test_run_schema.py) holds LOGISTICS_KEYS equal to conf/train.yaml's
`hydra.job.config.override_dirname.exclude_keys`; tests/test_architecture.py fails on a string literal
of a measured column's name outside this module.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pandas as pd


@dataclass(frozen=True)
class Column:
    """One column of a run table."""

    name: str
    """The column's name in the table (units in the name: `_mm`, `_rad`, `_radps`, `_s`)."""
    unit: str
    """The unit of its values ("" for counts, fractions and flags)."""
    label: str
    """What a report calls it (lower case, unit in parentheses)."""
    title: str = ""
    """Its short heading in `bmimic.eval`'s printed tables (the name when empty)."""


# --------------------------------------------------------------------------------------------- keys
ITERATION = "iteration"
"""The PPO iteration a row belongs to (train_metrics: the one that produced it; eval: after which it ran)."""
ENV_STEPS = "env_steps"
"""Environment steps taken before the row (all ranks together)."""
WALL_TIME_S = "wall_time_s"
"""Seconds of training before the row (collection and learning; evaluations not counted)."""
BIN = "bin"
"""The bin of the motion (a row of a per-bin table)."""

# --------------------------------------------------------------------------------------------- measures
TRACKING_ERRORS = (
    Column("mpkpe_mm", "mm", "global MPKPE (mm)", "MPKPE_mm"),
    Column("mpkpe_rel_mm", "mm", "root-relative MPKPE (mm)", "rel_MPKPE_mm"),
    Column("anchor_ori_err_rad", "rad", "anchor orientation error (rad)", "anchor_ori_rad"),
    Column("body_ori_err_rad", "rad", "body orientation error (rad)", "body_ori_rad"),
    Column("joint_pos_err_rad", "rad", "joint position error (rad)", "joint_pos_rad"),
    Column("joint_vel_err_radps", "rad/s", "joint velocity error (rad/s)", "joint_vel_radps"),
    Column("ee_pos_err_mm", "mm", "end-effector position error (mm)", "ee_pos_mm"),
)
"""Per-step tracking errors, in the order the evaluation measures them; a per-bin table holds their
means over the steps taken at the bin's frames."""
ERROR_COLUMNS = tuple(c.name for c in TRACKING_ERRORS)
(MPKPE_MM, MPKPE_REL_MM, ANCHOR_ORI_ERR_RAD, BODY_ORI_ERR_RAD, JOINT_POS_ERR_RAD, JOINT_VEL_ERR_RADPS,
 EE_POS_ERR_MM) = ERROR_COLUMNS
REPORTED_ERRORS = (MPKPE_REL_MM, MPKPE_MM, JOINT_POS_ERR_RAD, JOINT_VEL_ERR_RADPS, BODY_ORI_ERR_RAD, EE_POS_ERR_MM)
"""The tracking errors a comparison report shows, in its order (the anchor's is in the body's)."""

SMOOTHNESS = (
    Column("action_rate", "", "action rate (Σ over joints of (a_t − a_{t−1})², per step)"),
    Column("joint_acc_radps2", "rad/s²", "joint acceleration (rad/s², mean over joints)"),
)
"""Per-step smoothness of the policy itself (averaged like the errors): `action_rate` is the MDP's
action_rate_l2 term, sum over joints of (a_t - a_{t-1})^2 (a_{-1} = 0 at an episode's start);
`joint_acc_radps2` is the mean over joints of |qvel_t - qvel_{t-1}| / control period."""
SMOOTHNESS_COLUMNS = tuple(c.name for c in SMOOTHNESS)

LABELS = {c.name: c.label for c in (*TRACKING_ERRORS, *SMOOTHNESS)}
"""Measured column -> its report label."""

# --------------------------------------------------------------------------------------------- eval tables
EPISODE_COLUMNS = (
    "start_frame", "end_frame", "failed", "failure_frame", "terminated", "steps", "horizon_truncated",
)
"""Per-episode columns the per-bin aggregation reads (error means may follow): the first frame and the
last frame the episode was alive at (the clip's last frame for one that reached it), whether it failed
and at which frame (-1 if not), whether it terminated, steps alive, and whether its clip ends before
the horizon. An optional `broken` column marks episodes whose world broke (a failure, not a termination)."""

FAILURE_RATE = "failure_rate"
"""Per-bin table: failures per visit, charged to the bin where the failure happened."""
HORIZON_TRUNCATED = "horizon_truncated"
TRACKED_THROUGH = "tracked_through"
BIN_COLUMNS = (
    BIN, "visits", "failures", FAILURE_RATE, "start_episodes", "start_failures", "terminations",
    "tracking_failures", "broken", HORIZON_TRUNCATED, TRACKED_THROUGH, "eval_steps",
)
"""The counts of the per-bin evaluation table (eval.parquet after `iteration, env_steps, wall_time_s`;
eval/<label>/eval_bins.parquet), in order; the ERROR_COLUMNS and SMOOTHNESS_COLUMNS means follow."""

CLIP_ROLLOUT_COLUMNS = ("clip", "clip_name", "start_frame", "end_frame", "steps", "failed", "terminated", "broken",
                        "reached_end")
"""clip_eval.parquet's columns after `iteration, env_steps` (one row per clip and evaluation):
`end_frame` is the last frame the rollout was alive at; `reached_end` whether it tracked to the clip's
last frame (False for one cut by its time limit or failed)."""

ONNX_METADATA_VERSION = "3"
"""Version of the key set an exported ONNX's metadata holds (1: today's keys only; 2: BeyondMimic keys +
sim2sim keys; 3: + the clips' names and `time_step_input`): written by the export, required by sim2sim."""

# --------------------------------------------------------------------------------------------- whole clips
@dataclass(frozen=True)
class Condition:
    """What an evaluation perturbs, as data: every evaluator asks this, never the condition's name."""

    name: str
    perturbed: bool
    """Training's domain randomisation (startup and interval events: pushes) and observation noise on. A
    perturbed condition is random: many rollouts per clip, each its own draw. An unperturbed one is
    deterministic: one rollout per clip says all."""


CONDITIONS = {c.name: c for c in (Condition("nominal", perturbed=False), Condition("robust", perturbed=True))}
"""The evaluation conditions: `nominal` as the window evaluation (no domain randomisation, no observation
noise, no pushes), `robust` as in training (domain randomisation, observation noise and pushes)."""
WHOLE_CLIP_CONDITIONS = tuple(CONDITIONS)
"""The conditions a whole-clip evaluation may name (CONDITIONS)."""


def condition_rollouts(condition: str, perturbed_rollouts: int) -> int:
    """Rollouts per clip under `condition`: one when it is deterministic, else `perturbed_rollouts`."""
    return int(perturbed_rollouts) if CONDITIONS[condition].perturbed else 1
START_TRANSIENT_S = 1.0
"""A whole-clip rollout that fails within this many seconds of its start is a start transient."""
CONDITION = "condition"
CLIP_TIME_S = "time_s"
"""Seconds into the clip (its first frame at 0)."""
WHOLE_CLIP_SUCCESS = "success_rate"
"""Fraction of a clip's rollouts that tracked it to its last frame."""
WHOLE_CLIP_COLUMNS = (CONDITION, "clip", "clip_name", "clip_duration_s", "rollouts", "completed", WHOLE_CLIP_SUCCESS,
                      "failures", "transient_failures", "later_failures", "terminations", "tracking_failures", "broken",
                      "evaluation_s")
"""whole_clip.parquet's columns after `iteration, env_steps, wall_time_s` (one row per evaluation, condition
and clip; the means of ERROR_COLUMNS and SMOOTHNESS_COLUMNS over the completed rollouts follow, NaN when
none completed): R rollouts from the clip's first frame (bmimic.training.whole_clip); `failures` =
`transient_failures` (within START_TRANSIENT_S of the start) + `later_failures`, and = terminations +
tracking failures (eval.max_mpkpe_rel_mm) + broken worlds; `evaluation_s`: the wall time of the
condition's whole evaluation (all its clips)."""
WHOLE_CLIP_SURVIVAL_COLUMNS = (CONDITION, "clip", "clip_name", CLIP_TIME_S, "rollouts", "tracking", "tracking_frac")
"""A survival table of whole-clip rollouts (whole_clip_survival.parquet after `iteration, env_steps`;
`bmimic.eval --whole-clip`'s and sim2sim's whole_clip_survival.csv): per condition and clip, at every
whole second of it and at its last frame, the rollouts still tracking (no failure at or before that time)
and their fraction; at the last frame that is the clip's success rate. A view derived from the clips and
failures tables (whole_clip_survival below), written for whoever reads the files; the analysis derives it
again and analysis.compact drops it from committed runs."""
WHOLE_CLIP_FAILURE_COLUMNS = (CONDITION, "clip", "clip_name", "rollout", "failure_frame", "failure_time_s", BIN,
                              "transient", "terminated", "broken")
"""whole_clip_failures.parquet's columns after `iteration, env_steps`: one row per failed rollout, where
it failed (the motion frame the failure is charged to, its time into the clip and its bin), whether that
was a start transient, a termination or a broken world (neither: a tracking failure)."""
WHOLE_CLIP_SUMMARY_KEYS = ("success_rate", "rollouts", "completed", "transient_failures", "later_failures", "broken",
                           *ERROR_COLUMNS)
"""A whole-clip evaluation's summary per condition, each key named by `whole_clip_key` (over every clip;
errors: step-weighted over the completed rollouts); metrics.json holds the one at the end as
`final_<key>`."""


_COUNTS_WITHIN = (("failures", "visits"), ("start_failures", "start_episodes"), ("completed", "rollouts"))


def table_problems(name: str, table: "pd.DataFrame") -> list[str]:
    """What in a run table breaks its invariants (empty: none): counts negative or beyond their totals
    (failures within visits, start failures within start episodes), a failure rate that is not failures /
    visits, tracking errors negative, iterations and env steps not increasing row by row (train_metrics) or
    negative (every table), wall time going back (train_metrics). A damaged table is
    refused by its readers rather than reported as numbers it cannot hold."""
    import numpy as np

    def col(c: str) -> "np.ndarray | None":
        return table[c].to_numpy(dtype=float, na_value=np.nan) if c in table.columns else None

    out = []
    for c in (ITERATION, ENV_STEPS):
        v = col(c)
        if v is not None and (v < 0).any():
            out.append(f"column {c} negative")
    if name == "train_metrics":
        for c in (ITERATION, ENV_STEPS):
            v = col(c)
            if v is not None and len(v) > 1 and not (np.diff(v) > 0).all():
                out.append(f"column {c} not increasing from row to row")
        v = col(WALL_TIME_S)  # cumulative over a resumed run's launches: it never goes back
        if v is not None and len(v) > 1 and (np.diff(v) < 0).any():
            out.append(f"column {WALL_TIME_S} decreasing from row to row")
    for part, whole in _COUNTS_WITHIN:
        a, b = col(part), col(whole)
        if a is not None and ((a < 0).any() or (b is not None and (a > b).any())):
            out.append(f"column {part} negative or more than {whole}")
    for c in ERROR_COLUMNS:
        v = col(c)
        if v is not None and (v < 0).any():
            out.append(f"column {c} negative")
    rate, failures, visits = col(FAILURE_RATE), col("failures"), col("visits")
    if rate is not None and failures is not None and visits is not None:
        seen = visits > 0  # the rate is failures / visits, the unit every reader takes it in
        if (np.abs(rate[seen] - failures[seen] / visits[seen]) > 1e-6).any():
            out.append(f"column {FAILURE_RATE} not failures / visits")
    return out


def whole_clip_survival(clips: "pd.DataFrame", failures: "pd.DataFrame", keys: tuple[str, ...] = ()) -> "pd.DataFrame":
    """The survival view of whole-clip evaluations, derived from their two tables (the one rule for every
    writer and reader): per row of `clips` (WHOLE_CLIP_COLUMNS; one condition and clip of the evaluation
    that `keys` name, e.g. ITERATION), at every whole second of the clip and at its last frame, the rollouts
    still tracking, i.e. without a row in `failures` (WHOLE_CLIP_FAILURE_COLUMNS) at or before that time, and
    their fraction. Columns: `keys`, then WHOLE_CLIP_SURVIVAL_COLUMNS. Times compare at 1e-6 s (a control
    step is 0.02 s), so a failure at a listed time counts there; at the last frame the fraction is the
    clip's success rate."""
    import math

    import numpy as np
    import pandas as pd

    group = [*keys, CONDITION, "clip"]
    failed_at: dict[tuple, np.ndarray] = {}
    if len(failures):
        for key, df in failures.groupby(group, sort=False, dropna=False):
            failed_at[key] = np.sort(np.round(df["failure_time_s"].to_numpy(dtype=float), 6))
    none = np.zeros(0)
    parts = []
    for row in clips[[*group, "clip_name", "clip_duration_s", "rollouts"]].to_dict("records"):
        end_s = round(float(row["clip_duration_s"]), 6)
        times = np.unique(np.r_[np.arange(math.floor(end_s + 1e-9) + 1, dtype=float), end_s])
        fails = failed_at.get(tuple(row[c] for c in group), none)
        tracking = int(row["rollouts"]) - np.searchsorted(fails, times, side="right")
        parts.append(pd.DataFrame({**{c: row[c] for c in group}, "clip_name": row["clip_name"], CLIP_TIME_S: times,
                                   "rollouts": int(row["rollouts"]), "tracking": tracking.astype(np.int64)}))
    columns = [*keys, *WHOLE_CLIP_SURVIVAL_COLUMNS]
    if not parts:
        return pd.DataFrame(columns=columns)
    out = pd.concat(parts, ignore_index=True)
    out["tracking_frac"] = out["tracking"] / out["rollouts"].where(out["rollouts"] > 0)
    return out[columns]


def whole_clip_key(condition: str, key: str) -> str:
    """The summary name of `key` (one of WHOLE_CLIP_SUMMARY_KEYS) under `condition`: `whole_clip_<c>_<key>`."""
    return f"whole_clip_{condition}_{key}"


def whole_clip_success(summary: object, condition: str) -> float | None:
    """The whole-clip success rate of `condition` in a whole-clip summary of either shape, the one reader of
    both: MuJoCo-Warp's (bmimic.eval --whole-clip and training: flat `whole_clip_<condition>_success_rate`,
    `conditions` a list of names) and native MuJoCo's (bmimic.sim2sim --whole-clip: `conditions` a mapping of
    condition to its numbers). None: that condition was not evaluated. ValueError (one line): the summary is
    no mapping, or the rate is there but no fraction in [0, 1]."""
    if not isinstance(summary, dict):
        raise ValueError(f"a whole-clip summary is a JSON object, not {type(summary).__name__}")
    nested = summary.get("conditions")
    if isinstance(nested, dict):
        numbers = nested.get(condition)
        value = numbers.get("success_rate") if isinstance(numbers, dict) else None
    else:
        value = summary.get(whole_clip_key(condition, "success_rate"))
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
        raise ValueError(f"{condition} whole-clip success is {value!r}, not a fraction")
    return float(value)


# --------------------------------------------------------------------------------------------- metrics.json
EVAL_SUMMARY_KEYS = ("failure_rate", "bins_mastered_frac", "success_rate", "broken",
                     *ERROR_COLUMNS, *SMOOTHNESS_COLUMNS)
"""An evaluation's summary, each key prefixed `<prefix>_` (`eval_`, `robust_eval_`); metrics.json holds
the final one as `final_eval_<key>` (and `final_robust_eval_<key>` with eval.robust)."""


def summary_key(key: str, prefix: str = "eval") -> str:
    """The summary name of `key` (one of EVAL_SUMMARY_KEYS) under `prefix`."""
    return f"{prefix}_{key}"


FINAL_METRICS = tuple(f"final_{summary_key(k)}" for k in ("failure_rate", "success_rate", "mpkpe_mm",
                                                           "bins_mastered_frac"))
"""The final evaluation's numbers every metrics.json holds first."""
RUN_METRICS = ("iterations", "env_steps", "wall_time_s", "mean_episode_length", "max_episode_length", "num_bins",
               "num_envs", "device", "nonfinite_resets", "out_of_bounds_resets", "overflow_world_steps")
"""The rest of metrics.json: the run's budget, scale, broken-world totals and the world-steps whose
contact/constraint buffers overflowed (sim.nconmax / sim.njmax too small). A value that is not a
number (no episode ended: no mean length) is null."""

# --------------------------------------------------------------------------------------------- mastery
MASTERED_BELOW = 0.1
"""Failure rate (per visit) below which a bin counts as mastered in a run's own summary (the report's
default threshold)."""


def counts_as_mastered(per_bin: "pd.DataFrame", threshold: float = MASTERED_BELOW) -> "pd.Series":
    """Whether each row (one bin of one evaluation) counts as mastered: its failure rate is below
    `threshold` and, if the bin is horizon-truncated (its episodes run out of clip before the
    horizon), at least one episode tracked all of its frames after entering it from an earlier bin, so
    the clip's last bins are not "mastered" by a policy whose episodes simply run out of clip.

    Tables from before `horizon_truncated` existed are taken as not truncated.
    """
    below = per_bin[FAILURE_RATE].astype(float) < threshold
    if HORIZON_TRUNCATED not in per_bin:
        return below
    truncated = per_bin[HORIZON_TRUNCATED].fillna(False).astype(bool)
    through = per_bin[TRACKED_THROUGH].fillna(0) if TRACKED_THROUGH in per_bin else 0
    return below & (~truncated | (through >= 1))


# --------------------------------------------------------------------------------------------- logistics
BUDGET_KEYS = ("max_iterations", "num_envs", "time_limit_s")
"""The one set of config keys that say how much a run trains (iterations, worlds per iteration, wall
time): its results depend on them, yet no sweep makes arms of them (they stay out of job folder names),
so runs that differ in them are not one study's arms (a smoke run of 4 iterations is not a seed of a
10,000-iteration study). The analysis refuses to compare them (analysis.inputs) and lists them in a
sweep's index.csv; a resume may change all but num_envs (bmimic.training.resume.RESUME_BUDGET_KEYS)."""
LOGISTICS_KEYS = ("seed", "sweep_name", "run_name", "device", "resume", "sweep", "+sweep", "logger", "progress_bar",
                  *BUDGET_KEYS, "eval.every_iters", "ppo.save_interval",
                  "wandb_project", "verbose", "data.lafan_dir", "resume_allow_changes", "max_cpu_hours",
                  "stop_at_iteration")
"""Override keys that are budgets or logistics, not arms: they stay out of a sweep job's folder name
(conf/train.yaml's `hydra.job.config.override_dirname.exclude_keys`, which a test holds equal) and
out of the analysis's arm names."""


# ---------------------------------------------------------------------------------------------- race record
RACE_KIND = "bmimic-race-1"
"""The `kind` of RUN/race.json (bmimic.race writes it, analysis.races reads it); bumped when its layout changes."""
SUCCESS_RATE = "success_rate"
"""Evaluated success (0-1) in one evaluation record of a race (the evaluation summary's eval_success_rate)."""

# ---------------------------------------------------------------------------------------------- sim2sim whole clips
WHOLE_CLIP_ROLLOUT_COLUMNS = ("condition", "clip", "clip_name", "rollout", "completed", "failure_time_s", "transient",
                              "pushes")
"""sim2sim's whole-clip rollouts (sim2sim/<model>/<label>/whole_clip/eval_episodes.parquet), first columns,
then its episode columns: the condition, the clip and the rollout's index in it, whether it tracked to the
clip's last frame, when it failed (seconds into the clip; NaN if it did not), whether that was a start
transient (within START_TRANSIENT_S), and the pushes it took."""

__all__ = ["ANCHOR_ORI_ERR_RAD", "BIN", "BIN_COLUMNS", "BODY_ORI_ERR_RAD", "BUDGET_KEYS", "EE_POS_ERR_MM",
           "JOINT_POS_ERR_RAD", "JOINT_VEL_ERR_RADPS", "CLIP_ROLLOUT_COLUMNS", "CLIP_TIME_S", "CONDITION",
           "Column", "ENV_STEPS", "EPISODE_COLUMNS", "ERROR_COLUMNS", "EVAL_SUMMARY_KEYS", "FAILURE_RATE",
           "FINAL_METRICS", "HORIZON_TRUNCATED", "ITERATION", "LABELS", "LOGISTICS_KEYS", "MASTERED_BELOW",
           "MPKPE_MM", "MPKPE_REL_MM", "RACE_KIND", "REPORTED_ERRORS", "RUN_METRICS", "SMOOTHNESS",
           "SMOOTHNESS_COLUMNS", "START_TRANSIENT_S", "SUCCESS_RATE", "TRACKED_THROUGH", "TRACKING_ERRORS",
           "WALL_TIME_S", "WHOLE_CLIP_COLUMNS", "WHOLE_CLIP_CONDITIONS", "WHOLE_CLIP_FAILURE_COLUMNS",
           "WHOLE_CLIP_ROLLOUT_COLUMNS", "WHOLE_CLIP_SUCCESS", "WHOLE_CLIP_SUMMARY_KEYS",
           "WHOLE_CLIP_SURVIVAL_COLUMNS", "CONDITIONS", "Condition", "ONNX_METADATA_VERSION", "condition_rollouts",
           "counts_as_mastered", "summary_key", "whole_clip_key"]
