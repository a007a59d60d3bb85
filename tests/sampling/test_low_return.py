"""The low_return sampler, the feedback protocol's worked example: planted returns -> known probabilities."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from bmimic.sampling.config import load_variant, make_sampler, validate_sampler_config
from bmimic.sampling.feedback import SamplerFeedback
from bmimic.sampling.samplers import LowReturnConfig, LowReturnSampler
from bmimic.sampling.signals import EPISODE_RETURNS


def _expected(returns, temperature=1.0, lam=0.1):
    w = np.exp(-np.asarray(returns, dtype=float) / temperature)
    return lam / len(w) + (1 - lam) * w / w.sum()


def test_planted_mean_returns_give_the_softmax_probabilities():
    s = LowReturnSampler(3, LowReturnConfig(ema=0.5))
    np.testing.assert_allclose(s.probabilities().numpy(), [1 / 3] * 3)  # nothing seen: uniform
    s.update_returns(torch.tensor([[10.0, 2.0, 0.0]]), torch.tensor([2.0, 1.0, 0.0]))
    # means 5 and 2; bin 2 never visited counts as the lowest visited (2), so it is tried
    np.testing.assert_allclose(s.probabilities().numpy(), _expected([5, 2, 2]), rtol=1e-12)
    s.update_returns(torch.tensor([[0.0, 8.0, 3.0]]), torch.tensor([0.0, 2.0, 1.0]))
    # bin 0 holds 5; bin 1: 0.5 * 2 + 0.5 * 4 = 3; bin 2's first visit sets 3
    np.testing.assert_allclose(s.smoothed_failure().numpy(), [5, 3, 3])
    np.testing.assert_allclose(s.probabilities().numpy(), _expected([5, 3, 3]), rtol=1e-12)


def test_the_feedback_delivers_each_finished_episodes_return_to_its_start_bin():
    layout = SimpleNamespace(num_bins=3, num_clips=1, bins_of=lambda frames: frames // 10)
    s = LowReturnSampler(3, LowReturnConfig(ema=1.0, temperature=2.0))
    fb = SamplerFeedback(s, layout, num_envs=3, max_episode_length=100)
    assert fb.signals == (EPISODE_RETURNS,)
    fb.start_episodes(torch.ones(3, dtype=torch.bool), torch.tensor([0, 1, 2]))
    frames, no = torch.zeros(3, dtype=torch.long), torch.zeros(3, dtype=torch.bool)

    def errors():
        raise AssertionError("low_return does not declare the tracking errors")

    fb.measure(frames, no, no, torch.tensor([1.0, 2.0, 3.0]), errors)
    fb.measure(frames, no, torch.tensor([True, False, True]), torch.tensor([1.0, 0.0, 0.0]), errors)
    fb.measure(frames, no, torch.tensor([True, False, False]), torch.tensor([5.0, 0.0, 0.0]), errors)  # a new episode
    fb.end_rollout()
    # bin 0: episodes of return 2 and 5 (mean 3.5); bin 2: 3; bin 1: none finished (counts as the lowest, 3)
    np.testing.assert_allclose(s.smoothed_failure().numpy(), [3.5, 0.0, 3.0])
    np.testing.assert_allclose(s.probabilities().numpy(), _expected([3.5, 3, 3], temperature=2.0), rtol=1e-12)
    fb.end_rollout()  # the sums are cleared after each delivery: nothing new, nothing moves
    np.testing.assert_allclose(s.smoothed_failure().numpy(), [3.5, 0.0, 3.0])


def test_the_variant_composes_validates_and_round_trips_its_state():
    cfg = load_variant("low_return")
    validate_sampler_config(cfg, motion_duration_s=10.0)
    s = make_sampler(cfg, 4)
    assert isinstance(s, LowReturnSampler) and s.temperature == 1.0 and s.ema == 0.1
    s.update_returns(torch.tensor([[1.0, 0, 0, 4.0]]), torch.tensor([1.0, 0, 0, 2.0]))
    t = make_sampler(cfg, 4)
    t.load_state_dict(s.state_dict())
    assert torch.equal(t.probabilities(), s.probabilities()) and math.isclose(float(t.probabilities().sum()), 1.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_the_returns_hot_path_has_no_host_sync():
    """Measuring returns in the step, their per-iteration delivery and sampling never wait for the device."""
    from bmimic.sampling.bins import BinLayout

    dev, n = torch.device("cuda"), 4096
    layout = BinLayout(3000, 50.0, 1.0, device=dev)
    s = make_sampler(load_variant("low_return"), layout.num_bins, dev)
    fb = SamplerFeedback(s, layout, n, 500, device=dev)
    g = torch.Generator(device=dev).manual_seed(0)
    frames = torch.randint(0, 3000, (n,), device=dev, generator=g)
    done = torch.rand(n, device=dev, generator=g) < 0.1
    rewards = torch.rand(n, device=dev, generator=g)
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        fb.start_episodes(done, s.sample(n, generator=g))
        fb.measure(frames, done & ~done, done, rewards, lambda: None)
        fb.end_rollout()
        layout.sample_frames(s.sample(n, generator=g), generator=g)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    p = s.probabilities()
    assert torch.isfinite(p).all() and abs(float(p.sum()) - 1.0) < 1e-9
