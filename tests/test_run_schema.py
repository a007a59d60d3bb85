"""The run schema (bmimic.runs.schema): the contract between what a run writes and what reads it."""

from __future__ import annotations

import pandas as pd
import pytest

from analysis.metrics import ERROR_METRICS, SMOOTHNESS_METRICS
from analysis.run_files import IGNORED_OVERRIDE_KEYS
from bmimic.runs import schema as rs
from tests.conftest import compose


def test_logistics_keys_are_the_composed_configs_exclude_keys():
    cfg = compose(["sampler=uniform"], return_hydra_config=True)
    assert tuple(cfg.hydra.job.config.override_dirname.exclude_keys) == rs.LOGISTICS_KEYS


def test_the_analysis_ignores_every_logistics_key_in_arm_names():
    # The drift issue 34 found: the analysis lacked resume_allow_changes.
    assert set(rs.LOGISTICS_KEYS) <= IGNORED_OVERRIDE_KEYS
    assert {"resume_allow_changes", "max_cpu_hours"} <= IGNORED_OVERRIDE_KEYS


def test_every_measured_column_has_a_unit_in_its_name_and_a_label():
    for c in (*rs.TRACKING_ERRORS, *rs.SMOOTHNESS):
        assert c.label and c.label == rs.LABELS[c.name]
        if c.unit:
            assert f"({c.unit}" in c.label
    suffix = {"mm": "_mm", "rad": "_rad", "rad/s": "_radps"}
    assert all(c.name.endswith(suffix[c.unit]) for c in rs.TRACKING_ERRORS)
    assert set(rs.REPORTED_ERRORS) <= set(rs.ERROR_COLUMNS)


def test_readers_label_the_columns_the_producers_write():
    assert list(ERROR_METRICS) == list(rs.REPORTED_ERRORS)
    assert list(SMOOTHNESS_METRICS) == list(rs.SMOOTHNESS_COLUMNS)
    assert all(ERROR_METRICS[c] == rs.LABELS[c] for c in ERROR_METRICS)


def test_the_mastery_rule_on_planted_rows():
    rows = pd.DataFrame({rs.FAILURE_RATE: [0.05, 0.05, 0.05, 0.1, 0.0],
                         rs.HORIZON_TRUNCATED: [False, True, True, False, None],
                         rs.TRACKED_THROUGH: [0, 0, 2, 5, None]})
    # below the threshold; truncated needs one tracked-through episode; 0.1 is not below 0.1; NaN = not truncated
    assert rs.counts_as_mastered(rows).tolist() == [True, False, True, False, True]
    assert rs.counts_as_mastered(rows, threshold=0.2).tolist() == [True, False, True, True, True]
    assert rs.counts_as_mastered(rows[[rs.FAILURE_RATE]]).tolist() == [True, True, True, False, True]


def test_summary_keys_are_prefixed():
    assert rs.summary_key(rs.MPKPE_REL_MM) == "eval_mpkpe_rel_mm"
    assert rs.summary_key("failure_rate", "robust_eval") == "robust_eval_failure_rate"
    assert rs.FINAL_METRICS[0] == "final_eval_failure_rate"


def test_every_tracking_error_is_printed_under_its_own_title():
    # The printed evaluation table iterates the declarations (it once zipped them with a separate
    # tuple of titles, which would drop a column silently when one more error was declared).
    from bmimic.evaluation.report import _SHOWN
    from bmimic.runs.schema import TRACKING_ERRORS

    titles = [c.title for c in TRACKING_ERRORS]
    assert all(titles) and len(set(titles)) == len(titles)
    assert [_SHOWN[c.name][0] for c in TRACKING_ERRORS] == titles


def test_whole_clip_survival_is_derived_from_the_clips_and_failures_tables():
    """Known answers: a failure at a listed time counts there, the last frame's fraction is the clip's
    success, each evaluation (keys) sees only its own failures, and no failures leave every rollout tracking."""
    CLIP_TIME_S, CONDITION, ITERATION, whole_clip_survival = rs.CLIP_TIME_S, rs.CONDITION, rs.ITERATION, rs.whole_clip_survival
    clips = pd.DataFrame([{ITERATION: it, CONDITION: "robust", "clip": c, "clip_name": n, "clip_duration_s": d,
                           "rollouts": r} for it in (10, 20) for c, n, d, r in ((0, "dance", 2.58, 4), (1, "walk", 2.0, 2))])
    failures = pd.DataFrame([{ITERATION: 10, CONDITION: "robust", "clip": 0, "failure_time_s": 1.0},
                             {ITERATION: 10, CONDITION: "robust", "clip": 0, "failure_time_s": 2.3},
                             {ITERATION: 20, CONDITION: "robust", "clip": 0, "failure_time_s": 0.04}])
    sv = whole_clip_survival(clips, failures, keys=(ITERATION,))
    assert list(sv.columns) == [ITERATION, *rs.WHOLE_CLIP_SURVIVAL_COLUMNS]
    dance = sv[(sv[ITERATION] == 10) & (sv["clip"] == 0)]
    assert dance[CLIP_TIME_S].tolist() == [0.0, 1.0, 2.0, 2.58]
    assert dance["tracking"].tolist() == [4, 3, 3, 2] and dance["tracking_frac"].iloc[-1] == 0.5
    assert sv[(sv[ITERATION] == 20) & (sv["clip"] == 0)]["tracking"].tolist() == [4, 3, 3, 3]
    walk = sv[sv["clip"] == 1]
    assert walk[CLIP_TIME_S].tolist() == [0.0, 1.0, 2.0] * 2 and walk["tracking"].eq(2).all()
    none = whole_clip_survival(clips, failures.iloc[:0], keys=(ITERATION,))
    assert none["tracking_frac"].eq(1.0).all() and len(none) == len(sv)


# ------------------------------------------------------------------------------- whole-clip summaries
def test_one_reader_gives_the_same_success_from_both_whole_clip_summary_shapes():
    from bmimic.runs.schema import whole_clip_key, whole_clip_success

    warp = {"conditions": ["nominal", "robust"], whole_clip_key("nominal", "success_rate"): 1.0,
            whole_clip_key("robust", "success_rate"): 0.9375}
    native = {"conditions": {"robust": {"success_rate": 0.9375, "rollouts": 128}}}
    assert whole_clip_success(warp, "robust") == whole_clip_success(native, "robust") == 0.9375
    assert whole_clip_success(warp, "nominal") == 1.0
    assert whole_clip_success(native, "nominal") is None  # not evaluated: no number, no error
    assert whole_clip_success({"conditions": ["nominal"]}, "robust") is None
    assert whole_clip_success({"conditions": {"robust": 1}}, "robust") is None  # no numbers under it
    for bad in (1.5, -0.1, True, "0.9", float("nan")):
        for summary in ({whole_clip_key("robust", "success_rate"): bad}, {"conditions": {"robust": {"success_rate": bad}}}):
            with pytest.raises(ValueError, match="robust whole-clip success is .*not a fraction"):
                whole_clip_success(summary, "robust")
    with pytest.raises(ValueError, match="JSON object, not list"):
        whole_clip_success([0.9], "robust")
