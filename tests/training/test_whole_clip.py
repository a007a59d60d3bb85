"""Whole-clip evaluation (issue 44): R rollouts per clip from its first frame to its last, run by the
real Evaluator on planted environments whose failures are known, so every table has a planted answer:
completion, survival at every second, where failures fell (start transients apart from later ones),
errors over the completed rollouts; a robust condition's own draws per wave, which leave the caller's
random stream where it was; the schedule that decides when whole clips follow a window evaluation."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from bmimic.runs.schema import (
    BIN,
    CLIP_TIME_S,
    CONDITION,
    MPKPE_MM,
    WHOLE_CLIP_COLUMNS,
    WHOLE_CLIP_FAILURE_COLUMNS,
    WHOLE_CLIP_SURVIVAL_COLUMNS,
    whole_clip_key,
)
from bmimic.sampling.clips import ClipLayout
from bmimic.training.clip_rollouts import clip_start_rollouts
from bmimic.training.evaluator import Evaluator
from bmimic.training.schedule import WholeClipSchedule
from bmimic.training.whole_clip import (
    WholeClipEvaluation,
    clip_tables,
    own_random_stream,
    summarize_whole_clip,
)
from tests.training.test_clip_rollouts import FPS, PlantedEnv

STARTS, NUM_FRAMES = [0, 40, 70], 200  # clips of 0.8, 0.6 and 2.6 s (frames 0-39, 40-69, 70-199)


class ClipEnv(PlantedEnv):
    """PlantedEnv over STARTS / NUM_FRAMES: an env whose segment started in clip c terminates on its
    `fail_after[c]`-th step (never when 0); a robust env's rollout r (its world) fails on clip 2 after 60
    steps (1.2 s) when its world drew `doomed`; `redraw_startup_events` draws the worlds anew."""

    def __init__(self, num_envs: int, fail_after: dict[int, int], robust: bool = False):
        super().__init__(num_envs, set())
        self.clip_of_frame = torch.bucketize(torch.arange(NUM_FRAMES), torch.tensor(STARTS), right=True) - 1
        self.frame_clip_end = torch.tensor([*STARTS[1:], NUM_FRAMES])[self.clip_of_frame]
        self.fail_after = torch.tensor([fail_after.get(c, 0) for c in range(len(STARTS))])
        self.robust = self.perturbed = robust
        self.draw = torch.zeros(num_envs)
        self.redraws = []
        self._limit = torch.zeros(num_envs, dtype=torch.long)

    def redraw_startup_events(self) -> None:
        self.draw = torch.rand(self.num_envs)
        self.redraws.append(self.draw.clone())

    def reset_to_frames(self, frames: torch.Tensor) -> None:
        super().reset_to_frames(frames)
        limit = self.fail_after[self.clip_of_frame[self.time_steps]]
        if self.robust:  # a world that drew below 0.5 falls 1.2 s into clip 2
            limit = torch.where((self.clip_of_frame[self.time_steps] == 2) & (self.draw < 0.5), 60, limit)
        self._limit.copy_(limit)

    def step(self, actions: torch.Tensor):
        self._steps += 1
        self.time_steps.copy_(torch.minimum(self.time_steps + 1, self.segment_end - 1))
        self.reached_clip_end.copy_(self.time_steps >= self.segment_end - 1)
        terminated = (self._limit > 0) & (self._steps >= self._limit)
        extras = {"terminated": terminated, "broken": torch.zeros_like(terminated)}
        return self.get_observations(), torch.zeros(self.num_envs), terminated, extras


def _policy(obs, stochastic_output=False):
    return torch.zeros(obs.shape[0], 2)


def _layout() -> ClipLayout:
    return ClipLayout("time", STARTS, NUM_FRAMES, FPS, 0.5, clip_names=["walk", "jump", "dance"])


def _whole(num_envs: int, rollouts: int, conditions=("nominal", "robust"), fail_after=None) -> WholeClipEvaluation:
    layout = _layout()
    made = {}

    def make(condition: str, per_clip: int) -> Evaluator:
        made[condition] = per_clip
        env = ClipEnv(num_envs, fail_after if fail_after is not None else {1: 5}, robust=condition == "robust")
        return Evaluator(env, layout, [], 1, 4.0)

    whole = WholeClipEvaluation(make, layout, list(conditions), rollouts, seed=3, device="cpu")
    whole.made = made
    return whole


def test_nominal_runs_one_rollout_per_clip_to_its_last_frame_and_counts_a_start_transient():
    whole = _whole(8, rollouts=4, conditions=("nominal",))
    result = whole.evaluate(_policy)
    assert whole.made == {"nominal": 1}  # deterministic: one rollout per clip
    clips = result.clips.set_index("clip")
    assert list(result.clips.columns[: len(WHOLE_CLIP_COLUMNS)]) == list(WHOLE_CLIP_COLUMNS)
    assert clips["rollouts"].tolist() == [1, 1, 1] and clips["completed"].tolist() == [1, 0, 1]
    assert clips["clip_duration_s"].tolist() == pytest.approx([0.78, 0.58, 2.58])
    # clip 1 terminates on its 5th step: judged at its 4th frame, 0.08 s in: a start transient
    assert clips.loc[1, "transient_failures"] == 1 and clips.loc[1, "later_failures"] == 0
    assert clips.loc[1, "terminations"] == 1 and clips.loc[1, "tracking_failures"] == 0
    f = result.failures
    assert list(f.columns) == list(WHOLE_CLIP_FAILURE_COLUMNS) and len(f) == 1
    assert f.iloc[0]["failure_frame"] == 44 and f.iloc[0]["failure_time_s"] == pytest.approx(0.08)
    assert f.iloc[0][BIN] == whole.layout.frame_to_bin[44].item() and bool(f.iloc[0]["transient"])
    # errors over completed rollouts only: the planted state tracks perfectly (0 mm); clip 1: none completed
    assert clips.loc[0, MPKPE_MM] == 0.0 and math.isnan(clips.loc[1, MPKPE_MM])
    s = result.summary
    assert s[whole_clip_key("nominal", "success_rate")] == pytest.approx(2 / 3)
    assert s[whole_clip_key("nominal", "transient_failures")] == 1 and s[whole_clip_key("nominal", "later_failures")] == 0


def test_survival_at_every_second_and_at_the_last_frame():
    result = _whole(8, rollouts=4, conditions=("nominal",)).evaluate(_policy)
    sv = result.survival
    assert list(sv.columns) == list(WHOLE_CLIP_SURVIVAL_COLUMNS)
    dance = sv[sv["clip"] == 2]
    assert dance[CLIP_TIME_S].tolist() == [0.0, 1.0, 2.0, 2.58]
    assert dance["tracking_frac"].tolist() == [1.0] * 4
    jump = sv[sv["clip"] == 1]  # failed 0.08 s in: tracking at 0 s, not at its last frame
    assert jump[CLIP_TIME_S].tolist() == [0.0, 0.58] and jump["tracking"].tolist() == [1, 0]
    last = sv.groupby("clip").tail(1).set_index("clip")["tracking_frac"]
    np.testing.assert_allclose(last.to_numpy(), result.clips["success_rate"].to_numpy())


def test_robust_rollouts_each_draw_their_own_world_and_leave_the_callers_stream_alone():
    """4 robust rollouts per clip in an env of 4 worlds: 3 waves (one per clip), each redrawn from the
    run's seed and the wave; a world that drew below 0.5 falls 1.2 s into the dance, a later failure."""
    whole = _whole(4, rollouts=4, conditions=("robust",))
    torch.manual_seed(123)
    expected_next = torch.rand(3)
    torch.manual_seed(123)
    result = whole.evaluate(_policy)
    assert torch.equal(torch.rand(3), expected_next)  # the caller's stream did not move
    env = whole.evaluators["robust"].env
    assert len(env.redraws) == 3 and not torch.equal(env.redraws[0], env.redraws[2])
    doomed = int((env.redraws[2] < 0.5).sum())  # the dance ran in the third wave
    clips = result.clips.set_index("clip")
    assert clips["rollouts"].tolist() == [4, 4, 4]
    assert clips.loc[2, "completed"] == 4 - doomed and clips.loc[2, "later_failures"] == doomed
    assert clips.loc[1, "transient_failures"] == 4
    dance = result.failures[result.failures["clip"] == 2]
    assert dance["failure_time_s"].tolist() == pytest.approx([1.18] * doomed) and not dance["transient"].any()
    sv = result.survival[result.survival["clip"] == 2].set_index(CLIP_TIME_S)["tracking"]
    assert sv[1.0] == 4 and sv[2.0] == 4 - doomed
    again = _whole(4, rollouts=4, conditions=("robust",)).evaluate(_policy)  # the same draws: reproducible
    pd.testing.assert_frame_equal(again.failures, result.failures)


def test_a_rollout_cut_short_is_an_error_not_a_success():
    layout = _layout()
    env = ClipEnv(3, {})
    ev = Evaluator(env, layout, [], 1, 4.0)
    episodes = clip_start_rollouts(ev, _policy, 1).episodes
    episodes.loc[2, "end_frame"] -= 10  # as if a time limit had stopped it before the dance's end
    with pytest.raises(ValueError, match="cut short"):
        clip_tables(episodes, "nominal", layout, 1 / FPS)


def test_the_summary_weights_errors_by_completed_steps():
    clips = pd.DataFrame({CONDITION: ["robust"] * 2, "rollouts": [4, 2], "completed": [3, 0], "clip_duration_s": [2.0, 1.0],
                          "transient_failures": [1, 0], "later_failures": [0, 2], "broken": [0, 1],
                          MPKPE_MM: [30.0, math.nan]})
    s = summarize_whole_clip(clips)
    assert s[whole_clip_key("robust", "success_rate")] == pytest.approx(0.5)
    assert s[whole_clip_key("robust", MPKPE_MM)] == pytest.approx(30.0)
    assert s[whole_clip_key("robust", "later_failures")] == 2 and s[whole_clip_key("robust", "rollouts")] == 6


def test_own_random_stream_is_seeded_and_restores():
    torch.manual_seed(0)
    with own_random_stream(5, "cpu"):
        inside = torch.rand(2)
    after = torch.rand(2)
    torch.manual_seed(5)
    assert torch.equal(inside, torch.rand(2))
    torch.manual_seed(0)
    assert torch.equal(after, torch.rand(2))


@pytest.mark.parametrize("sched,calls,expected", [
    # a fixed cadence, open from the start: every 200 iterations
    (dict(every=200, max_share=None, after_success=None), [(100, 0.5, 1, 100, 50), (200, 0.5, 1, 200, 50)],
     [False, True]),
    # closed until the windows reach 0.95, then open for good, even when they dip again
    (dict(every=100, max_share=None, after_success=0.95), [(100, 0.9, 1, 100, 5), (200, 0.96, 1, 200, 5),
                                                          (300, 0.9, 1, 300, 5)], [False, True, True]),
    # the share rule: 10 s so far + 50 s of whole clips within 10% of 500 + 50 s? no; of 600 + 50 s? yes
    (dict(every=0, max_share=0.10, after_success=None), [(100, 0.99, 10, 500, 50), (200, 0.99, 10, 600, 50)],
     [False, True]),
])
def test_the_whole_clip_schedule(sched, calls, expected):
    s = WholeClipSchedule(**sched)
    assert [s.due(*c) for c in calls] == expected


# --------------------------------------------------------------------------------------------- the real environment
def test_the_real_evaluation_env_holds_a_whole_clip_past_trainings_episode_limit_and_redraws_its_worlds():
    """Training's episode limit is 0.2 s; the whole-clip environments' is derived from the 7 s clip, so a
    rollout (zero actions: the default pose) runs until it falls, past 0.2 s. A robust environment's
    worlds redraw their domain randomisation from the nominal model: the same seed, the same draw."""
    from bmimic.config import resolve_runtime
    from bmimic.task import build_task, build_whole_clip
    from tests.conftest import compose

    cfg = compose(["device=cpu", "motion=easy_only", "motion.duration_s=7", "env.episode_length_s=0.2",
                   "eval.whole_clip.rollouts=2"])
    resolve_runtime(cfg, "cpu")
    task = build_task(cfg, "cpu")
    whole = build_whole_clip(task)
    assert whole.steps() == 349
    env = whole.evaluator("nominal").env
    assert env.max_episode_length >= whole.steps() > 10
    result = whole.evaluate(lambda obs, stochastic_output=False: torch.zeros(obs["policy"].shape[0], 29))
    assert result.clips["rollouts"].tolist() == [1, 2]
    ended = result.clips["completed"] + result.clips["failures"]
    assert ended.tolist() == [1, 2]  # every rollout completed or failed: none was cut short
    assert (result.failures["failure_time_s"] > 0.2).all()  # each outlived training's 0.2 s episode
    robust = whole.evaluator("robust").env
    draws = []
    for seed in (1, 1, 2):
        torch.manual_seed(seed)
        robust.redraw_startup_events()
        draws.append((robust.sim.geom_friction.clone(), robust.default_joint_pos.clone()))
    assert torch.equal(draws[0][0], draws[1][0]) and torch.equal(draws[0][1], draws[1][1])
    assert not torch.equal(draws[0][0], draws[2][0])
    robust.sim.restore_model_fields(robust.events.model_fields)
    np.testing.assert_allclose(robust.sim.geom_friction[1].numpy(), task.mjm.geom_friction, rtol=1e-6)
    whole.close()


def test_a_clip_longer_than_the_evaluation_holds_is_refused_in_one_line():
    from bmimic.config import ConfigError, resolve_runtime
    from bmimic.task import build_task, build_whole_clip
    from tests.conftest import compose

    cfg = compose(["device=cpu", "motion=easy_only", "motion.duration_s=7", "eval.whole_clip.max_clip_s=5"])
    resolve_runtime(cfg, "cpu")
    with pytest.raises(ConfigError, match=r"max_clip_s: clip 'easy_only' is 6.98 s long, longer than the 5 s") as e:
        build_whole_clip(build_task(cfg, "cpu"))
    assert "never cut short" in str(e.value) and len(str(e.value).splitlines()) == 1
