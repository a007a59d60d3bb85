"""The evaluation-driven samplers' signal (issue 31): one rollout per clip from its first frame, run by
the real Evaluator on a planted library whose clip 1 always fails and whose other clips never do; the
failing clip's sampling mass must grow under PHC and ProtoMotions, and PHC resets to uniform over clips
when an evaluation fails no clip."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from bmimic.sampling import PHCSampler, ProtoMotionsSampler
from bmimic.sampling.clips import ClipLayout
from bmimic.sampling.peer_clips import PHCConfig
from bmimic.training.clip_rollouts import clip_bounds, clip_rollouts, clips_failed
from bmimic.training.evaluator import Evaluator

FPS = 50.0
STARTS, NUM_FRAMES = [0, 40, 70], 100  # clips of 0.8, 0.6 and 0.6 s
FAIL_AFTER = 5  # steps after which an env on a failing clip terminates


class PlantedEnv:
    """The part of the evaluation environment the Evaluator uses: frames advance one per step and hold
    at the clip's last frame; an env whose segment started in a clip of ``failing`` terminates on its
    FAIL_AFTER-th step; the state is the reference's (no tracking error)."""

    perturbed = False
    """As TrackingEnv.perturbed: no events, no observation noise (a nominal evaluation)."""

    def __init__(self, num_envs: int, failing: set[int]):
        self.num_envs, self.device, self.step_dt = num_envs, torch.device("cpu"), 1.0 / FPS
        starts = torch.tensor(STARTS)
        self.clip_of_frame = torch.bucketize(torch.arange(NUM_FRAMES), starts, right=True) - 1
        self.frame_clip_end = torch.tensor([*STARTS[1:], NUM_FRAMES])[self.clip_of_frame]
        self.failing = torch.tensor([c in failing for c in range(len(STARTS))])
        self.time_steps = torch.zeros(num_envs, dtype=torch.long)
        self.segment_end = torch.full((num_envs,), NUM_FRAMES)
        self.reached_clip_end = torch.zeros(num_envs, dtype=torch.bool)
        self._steps = torch.zeros(num_envs, dtype=torch.long)
        self._fails = torch.zeros(num_envs, dtype=torch.bool)
        self.actions = torch.zeros(num_envs, 2)
        self.last_actions = torch.zeros(num_envs, 2)
        z3, q = torch.zeros(num_envs, 3, 3), torch.tensor([1.0, 0, 0, 0]).expand(num_envs, 3, 4)
        self.state = SimpleNamespace(
            ref_body_pos=z3, robot_body_pos=z3, ref_anchor_pos=z3[:, 0], robot_anchor_pos=z3[:, 0], ref_body_quat=q,
            robot_body_quat=q, ref_body_quat_relative=q, ref_body_pos_relative=z3, ref_joint_pos=torch.zeros(num_envs, 2),
            joint_pos=torch.zeros(num_envs, 2), ref_joint_vel=torch.zeros(num_envs, 2), joint_vel=torch.zeros(num_envs, 2))
        self.bodies = SimpleNamespace(anchor=0, end_effectors=[1, 2])

    def reset_to_frames(self, frames: torch.Tensor) -> None:
        self.time_steps.copy_(frames.long())
        self.segment_end.copy_(self.frame_clip_end[self.time_steps])
        self._fails.copy_(self.failing[self.clip_of_frame[self.time_steps]])
        self._steps.zero_()
        self.reached_clip_end.zero_()

    def get_observations(self) -> torch.Tensor:
        return torch.zeros(self.num_envs, 1)

    def step(self, actions: torch.Tensor):
        self._steps += 1
        self.time_steps.copy_(torch.minimum(self.time_steps + 1, self.segment_end - 1))
        self.reached_clip_end.copy_(self.time_steps >= self.segment_end - 1)
        terminated = self._fails & (self._steps >= FAIL_AFTER)
        extras = {"terminated": terminated, "broken": torch.zeros_like(terminated)}
        return self.get_observations(), torch.zeros(self.num_envs), terminated, extras


def _policy(obs, stochastic_output=False):
    return torch.zeros(obs.shape[0], 2)


def _evaluator(failing: set[int]) -> Evaluator:
    layout = ClipLayout("time", STARTS, NUM_FRAMES, FPS, 0.2, clip_names=["walk", "jump", "run"])
    return Evaluator(PlantedEnv(4, failing), layout, [], episodes_per_bin=2, horizon_s=0.2)


def test_one_rollout_per_clip_from_its_first_frame_to_its_end():
    ev = _evaluator({1})
    assert [list(x) for x in clip_bounds(ev.layout)] == [STARTS, [40, 70, 100]]
    rows = clip_rollouts(ev, _policy)
    assert rows["clip_name"].tolist() == ["walk", "jump", "run"]
    assert rows["start_frame"].tolist() == STARTS
    assert rows["failed"].tolist() == [False, True, False]
    assert rows["reached_end"].tolist() == [True, False, True]
    assert rows["end_frame"].tolist() == [39, 40 + FAIL_AFTER - 1, 99]  # the whole clip, longer than horizon_s
    assert clips_failed(rows, 3).tolist() == [False, True, False]
    # rollout_max_s cuts every rollout: 0.06 s = 3 steps, before clip 1's failure and every clip's end
    short = clip_rollouts(ev, _policy, max_s=0.06)
    assert short["failed"].tolist() == [False] * 3 and not short["reached_end"].any()
    assert short["steps"].tolist() == [3, 3, 3]


@pytest.mark.parametrize("make", [lambda s: PHCSampler(s, PHCConfig(mode="soft")),
                                  lambda s: PHCSampler(s, PHCConfig(mode="hard")),
                                  ProtoMotionsSampler], ids=["phc_soft", "phc_hard", "protomotions"])
def test_the_always_failing_clip_gains_mass(make):
    ev = _evaluator({1})
    sampler = make(ev.layout.num_bins)
    sampler.set_clips(ev.layout.bin_clip, ev.layout.bin_last_in_clip, 3)
    clip = ev.layout.bin_clip.numpy()
    masses = [float(sampler.probabilities().numpy()[clip == 1].sum())]
    for _ in range(8):
        sampler.observe_eval(clips_failed(clip_rollouts(ev, _policy), 3), 200)
        masses.append(float(sampler.probabilities().numpy()[clip == 1].sum()))
    assert masses[0] == pytest.approx(1 / 3)  # uniform over clips before any evaluation
    assert np.all(np.diff(masses) >= -1e-12) and masses[-1] > masses[0] + 0.2
    if isinstance(sampler, PHCSampler):
        assert masses[-1] == pytest.approx(1.0)  # h = [0, k, 0]: every start on the failing clip
    else:
        assert masses[-1] == pytest.approx(1 / (1 + 2 / 3))  # the others decayed to the floor 1/3


def test_phc_resets_to_uniform_when_nothing_failed_and_keeps_its_counts():
    layout = _evaluator(set()).layout
    s = PHCSampler(layout.num_bins)
    s.set_clips(layout.bin_clip, layout.bin_last_in_clip, 3)
    clip = layout.bin_clip.numpy()

    def mass():
        p = s.probabilities().numpy()
        return [float(p[clip == c].sum()) for c in range(3)]

    s.observe_eval(torch.tensor([False, True, False]), 10)
    np.testing.assert_allclose(mass(), [0, 1, 0], atol=1e-12)
    s.observe_eval(clips_failed(clip_rollouts(_evaluator(set()), _policy), 3), 10)  # nothing failed
    np.testing.assert_allclose(mass(), [1 / 3] * 3)
    s.observe_eval(torch.tensor([True, False, False]), 10)  # h = [1, 1, 0]: the history is kept
    np.testing.assert_allclose(mass(), [0.5, 0.5, 0], atol=1e-12)


class CountingEnv(PlantedEnv):
    def __init__(self, num_envs: int, failing: set[int], robust: bool = False):
        super().__init__(num_envs, failing)
        self.perturbed, self.steps_taken = robust, 0

    def step(self, actions: torch.Tensor):
        self.steps_taken += 1
        return super().step(actions)


@pytest.mark.parametrize("robust", [False, True])
def test_a_wave_stops_when_no_episode_is_alive_and_measures_the_same(monkeypatch, robust):
    """Every episode ends by step 40 (clip ends, clip 1's failure); the horizon is 200 steps. A
    deterministic env stops at the first check after that (step 50) with the same tables; a robust one
    (its draws advance torch's generator) runs the whole horizon."""
    from bmimic.training import evaluator as evaluator_module

    def run(check_steps: int):
        monkeypatch.setattr(evaluator_module, "ALIVE_CHECK_STEPS", check_steps)
        layout = ClipLayout("time", STARTS, NUM_FRAMES, FPS, 0.2, clip_names=["walk", "jump", "run"])
        env = CountingEnv(16, {1}, robust=robust)
        out = Evaluator(env, layout, [], episodes_per_bin=2, horizon_s=4.0).run_episodes(_policy)
        return out, env.steps_taken

    (early, n_early), (full, n_full) = run(50), run(10**9)
    assert n_full == 2 * 200  # 10 bins x 2 episodes: two waves of 16 envs, 200 steps each
    assert n_early == (2 * 200 if robust else 2 * 50)
    pd.testing.assert_frame_equal(early.episodes, full.episodes)
    pd.testing.assert_frame_equal(early.frame_errors, full.frame_errors)
