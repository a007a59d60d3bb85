"""The train/eval difference of TrackingEnv lives in its episodes object (SampledEpisodes or
PlacedEpisodes); the constructor refuses combinations that would mean something else."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from bmimic.envs.episodes import PlacedEpisodes
from bmimic.envs.tracking_env import TrackingEnv


@pytest.mark.parametrize("mode, feedback, robust, message", [
    ("play", None, False, "mode must be train or eval"),
    ("train", None, False, "needs the sampler's feedback"),
    ("eval", object(), False, "needs the sampler's feedback"),
    ("train", object(), True, "robust is an evaluation's option"),
])
def test_the_constructor_refuses_what_it_cannot_mean(mode, feedback, robust, message):
    with pytest.raises(ValueError, match=message):
        TrackingEnv(None, None, None, None, None, 4, "cpu", feedback=feedback, mode=mode, robust=robust)  # type: ignore[arg-type]


@pytest.mark.parametrize("robust, pushes", [(False, False), (True, False), (True, True)])
def test_an_evaluation_perturbs_only_when_robust_and_moves_worlds_only_by_pushes(robust, pushes):
    episodes = PlacedEpisodes(robust, layout=None)
    env = SimpleNamespace(events=SimpleNamespace(has_interval=pushes))
    assert episodes.perturbed is robust and episodes.places_worlds and episodes.feedback is None
    assert episodes.kinematics_after_step(env) is pushes  # type: ignore[arg-type]
    assert episodes.pop_counts() == (None, None)
