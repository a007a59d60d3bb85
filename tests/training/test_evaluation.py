"""The evaluation's accounting: failures charged to the bin where they happen, visits, horizon
truncation, tracking failures, and the robust evaluation environment.

Known answers from hand-built episodes (training/evaluation.aggregate), then a real evaluation
environment on the CPU whose terminations are planted at a chosen frame, checked against an
independent frame-by-frame count.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from bmimic.training.evaluator import BIN_COLUMNS, aggregate

# 3 bins of 10 frames each.
FRAME_TO_BIN = np.repeat([0, 1, 2], 10)


def _episodes(rows) -> pd.DataFrame:
    cols = ["start_frame", "end_frame", "failed", "failure_frame", "terminated", "steps", "horizon_truncated"]
    return pd.DataFrame(rows, columns=cols)


def test_failure_is_charged_where_it_happens():
    # Starts in bin 0 (frame 5), fails at frame 14 (bin 1); a survivor runs from bin 1 into bin 2.
    ep = _episodes([(5, 14, True, 14, True, 10, False), (15, 24, False, -1, False, 10, False)])
    t = aggregate(ep, FRAME_TO_BIN).set_index("bin")
    assert list(t.reset_index().columns[: len(BIN_COLUMNS)]) == list(BIN_COLUMNS)
    assert t["failures"].tolist() == [0, 1, 0]  # bin 1, not the start bin 0
    assert t["visits"].tolist() == [1, 2, 1]
    assert t["failure_rate"].tolist() == [0.0, 0.5, 0.0]
    assert t["start_episodes"].tolist() == [1, 1, 0] and t["start_failures"].tolist() == [1, 0, 0]
    assert t["terminations"].tolist() == [0, 1, 0] and t["tracking_failures"].tolist() == [0, 0, 0]
    assert np.isnan(aggregate(ep.iloc[:0], FRAME_TO_BIN)["failure_rate"]).all()  # no visit: no rate


def test_tracked_through_counts_only_whole_bins_entered_from_before():
    ep = _episodes([
        (5, 29, False, -1, False, 24, True),  # from bin 0 through the last frame of bins 1 and 2
        (10, 29, False, -1, False, 19, True),  # starts at bin 1's first frame: bin 1 not "entered"
        (5, 27, True, 27, True, 23, False),  # fails inside bin 2: tracked through bin 1 only
        (20, 22, False, -1, False, 3, True),  # starts in bin 2 and stops early
    ])
    t = aggregate(ep, FRAME_TO_BIN).set_index("bin")
    assert t["tracked_through"].tolist() == [0, 2, 2]
    assert t["horizon_truncated"].tolist() == [True, True, True]
    assert t["visits"].tolist() == [2, 3, 4]


def test_tracking_failure_and_defaults():
    # A tracking failure (mean error too high) is charged at its failure_frame; without the optional
    # columns a failure is charged at end_frame and counts as a termination.
    ep = _episodes([(0, 19, True, 3, False, 20, False)])
    t = aggregate(ep, FRAME_TO_BIN)
    assert t["failures"].tolist() == [1, 0, 0] and t["tracking_failures"].tolist() == [1, 0, 0]
    plain = aggregate(ep[["start_frame", "end_frame", "failed"]], FRAME_TO_BIN)
    assert plain["failures"].tolist() == [0, 1, 0] and plain["terminations"].tolist() == [0, 1, 0]
    assert not plain["horizon_truncated"].any()


def test_a_broken_world_is_a_failure_of_its_own_kind():
    ep = _episodes([(5, 14, True, 14, False, 10, False), (15, 24, True, 22, True, 8, False)])
    ep["broken"] = [True, False]
    t = aggregate(ep, FRAME_TO_BIN)
    assert t["failures"].tolist() == [0, 1, 1]
    assert t["broken"].tolist() == [0, 1, 0]
    assert t["terminations"].tolist() == [0, 0, 1] and t["tracking_failures"].tolist() == [0, 0, 0]
    ep["failed"] = [False, True]
    with pytest.raises(ValueError, match="broke must count as failed"):
        aggregate(ep, FRAME_TO_BIN)


def test_frame_errors_average_per_step_where_they_were_measured():
    ep = _episodes([(0, 19, False, -1, False, 20, False)])
    errors = pd.DataFrame({"steps": np.r_[np.ones(20), np.zeros(10)], "mpkpe_mm": np.r_[np.full(10, 10.0),
                                                                                        np.full(10, 30.0), np.zeros(10)]})
    t = aggregate(ep, FRAME_TO_BIN, errors)
    assert t["eval_steps"].tolist() == [10, 10, 0]
    np.testing.assert_allclose(t["mpkpe_mm"].to_numpy()[:2], [10.0, 30.0])
    assert np.isnan(t["mpkpe_mm"].iloc[2])


@pytest.mark.parametrize("bad, message", [
    (dict(end_frame=40), "0 <= start_frame <= end_frame < 30"),
    (dict(end_frame=2), "0 <= start_frame <= end_frame"),
    (dict(failure_frame=1), "failure_frame must lie between"),
])
def test_bad_episode_rows_are_one_line_errors(bad, message):
    row = dict(start_frame=5, end_frame=14, failed=True, failure_frame=14, terminated=True, steps=10,
               horizon_truncated=False)
    with pytest.raises(ValueError, match=message):
        aggregate(pd.DataFrame([{**row, **bad}]), FRAME_TO_BIN)
    with pytest.raises(ValueError, match="lack columns"):
        aggregate(pd.DataFrame([row]).drop(columns=["failed"]), FRAME_TO_BIN)
    with pytest.raises(ValueError, match="non-decreasing"):
        aggregate(pd.DataFrame([row]), FRAME_TO_BIN[::-1])


# --------------------------------------------------------------------------------------------- real env
class PlantedTermination:
    """An evaluation env whose terminations are replaced by one planted frame: an episode terminates
    exactly when the frame it is judged at equals `frame` (the real physics still runs)."""

    def __init__(self, env, frame: int) -> None:
        self._env = env
        self._frame = frame

    def __getattr__(self, name):
        return getattr(self._env, name)

    def step(self, actions):
        judged = self._env.time_steps.clone()
        obs, rew, dones, extras = self._env.step(actions)
        return obs, rew, dones, {**extras, "terminated": judged == self._frame}


@pytest.fixture(scope="module")
def robust_evaluator():
    from bmimic.config import resolve_runtime
    from bmimic.runtime import seed_everything
    from bmimic.task import build_evaluator, build_task
    from tests.conftest import compose

    seed_everything(0)
    cfg = compose(["motion=easy_only", "motion.duration_s=7", "sampler.bin_size_seconds=1.0", "device=cpu",
                   "eval.episodes_per_bin=1", "eval.horizon_s=1.0"])
    resolve_runtime(cfg, "cpu")
    return build_evaluator(build_task(cfg, "cpu"), robust=True)


def _expected(starts, horizon, clip_end, planted, per_bin=50, num_bins=7):
    """Frame-by-frame oracle: per bin visits and failures for episodes starting at `starts`."""
    visits, failures = np.zeros(num_bins, int), np.zeros(num_bins, int)
    for f0 in starts:
        seen = set()
        frame = f0
        for _ in range(horizon):
            seen.add(frame // per_bin)
            if frame == planted:
                failures[frame // per_bin] += 1
                break
            frame += 1
            if frame >= clip_end - 1:  # the reference stops at the clip's last frame
                seen.add(frame // per_bin)
                break
        for b in seen:
            visits[b] += 1
    return visits, failures


def test_real_eval_env_charges_the_bin_where_the_planted_termination_happens(robust_evaluator):
    ev = robust_evaluator
    env = ev.env
    # DR, noise and pushes on, as in training
    assert env.episodes.perturbed and env.events.model_fields and env.events.has_interval and env.observations.noisy["policy"]
    assert env.perturbed  # what the evaluator asks (a robust wave keeps stepping: its draws advance torch's stream)
    assert ev.layout.num_bins == 7 and ev.horizon_steps == 50
    planted = 60  # bin 1; the episode started in bin 0 (frame 25) runs into it
    ev.env = PlantedTermination(env, planted)
    try:
        rollouts = ev.run_episodes(lambda obs, stochastic_output=False: torch.zeros(env.num_envs, env.num_actions))
    finally:
        ev.env = env
    ep = rollouts.episodes
    assert ep["start_frame"].tolist() == list(range(25, 350, 50))
    hit = ep[ep["failed"]]
    assert hit["start_frame"].tolist() == [25] and hit["failure_frame"].tolist() == [60]
    assert hit["steps"].tolist() == [36]
    per_bin = ev.bin_table(rollouts)
    visits, failures = _expected(ep["start_frame"], 50, 350, planted)
    assert per_bin["failures"].tolist() == failures.tolist() == [0, 1, 0, 0, 0, 0, 0]
    assert per_bin["visits"].tolist() == visits.tolist()
    assert per_bin["start_failures"].tolist() == [1] + [0] * 6
    # Only the episode from frame 325 reaches the clip end (frame 349) within 50 steps.
    assert per_bin["horizon_truncated"].tolist() == [False] * 6 + [True]
    # A 1 s horizon cannot cover a whole 1 s bin after entering it (the episode from frame 275 stops at
    # 324, before bin 6 ends), so the truncated bin can never count as mastered with these settings.
    assert (per_bin["tracked_through"] == 0).all()
    assert int(per_bin["eval_steps"].sum()) == int(ep["steps"].sum())
    assert np.isfinite(per_bin["mpkpe_mm"]).all()


def test_robust_env_pushes_the_robot(robust_evaluator):
    env = robust_evaluator.env
    env.reset_to_frames(torch.full((env.num_envs,), 5))
    (push_timer_s,) = env.events.time_left_s
    push_timer_s.fill_(0.0)  # every world is due a push on the next step
    before = push_timer_s.clone()
    env.step(torch.zeros(env.num_envs, env.num_actions))
    assert (push_timer_s > before).all()  # pushed, and the next push drawn


def test_a_policy_that_breaks_the_simulation_fails_every_episode(robust_evaluator):
    # NaN actions make every world non-finite on the first step: the environment resets those worlds
    # (a time-out for PPO), and the evaluation must count each as a failure, never as tracking.
    from bmimic.training.evaluator import summarize

    ev = robust_evaluator
    env = ev.env
    rollouts = ev.run_episodes(lambda obs, stochastic_output=False: torch.full((env.num_envs, env.num_actions), math.nan))
    ep = rollouts.episodes
    assert ep["failed"].all() and ep["broken"].all() and not ep["terminated"].any()
    assert (ep["failure_frame"] == ep["start_frame"]).all() and (ep["steps"] == 0).all()
    summary = summarize(ev.bin_table(rollouts))
    assert summary["eval_success_rate"] == 0.0 and summary["eval_broken"] == len(ep)
    assert summary["eval_bins_mastered_frac"] == 0.0


def test_smoothness_is_the_policy_own_action_rate_and_joint_acceleration(robust_evaluator):
    # A constant action c: the action rate is sum(c^2) on an episode's first step (a_-1 = 0) and 0
    # after, so an episode's per-step mean times its measured steps is 29 c^2.
    ev = robust_evaluator
    env = ev.env
    c = 0.1
    rollouts = ev.run_episodes(lambda obs, stochastic_output=False: torch.full((env.num_envs, env.num_actions), c))
    ep = rollouts.episodes[lambda d: d["steps"] > 0]
    assert len(ep)
    np.testing.assert_allclose(ep["action_rate"] * ep["steps"], env.num_actions * c * c, rtol=1e-5)
    assert (ep["joint_acc_radps2"] > 0).all() and np.isfinite(ep["joint_acc_radps2"]).all()
    per_bin = ev.bin_table(rollouts)
    assert {"action_rate", "joint_acc_radps2", "broken"} <= set(per_bin.columns)
