"""Bins over a motion library (bmimic.sampling.clips) and the samplers' clip awareness."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from bmimic.sampling.clips import ClipLayout
from bmimic.sampling.config import make_sampler, sampler_config
from bmimic.sampling.layouts import make_layout
from bmimic.sampling.samplers import AdaptiveConfig, AdaptiveSampler, UniformSampler

FPS = 50.0


def _starts(lengths: list[int]) -> list[int]:
    out, acc = [], 0
    for n in lengths:
        out.append(acc)
        acc += n
    return out


@settings(max_examples=60, deadline=None)
@given(lengths=st.lists(st.integers(2, 400), min_size=2, max_size=6),
       bin_size=st.sampled_from([0.02, 0.1, 0.25, 0.5, 1.0, 1.3, 3.0]), kind=st.sampled_from(["time", "released"]))
def test_the_global_bin_mapping_goes_both_ways_and_never_spans_clips(lengths, bin_size, kind):
    bin_size = max(bin_size, 1.0 / FPS)
    layout = make_layout(kind, sum(lengths), FPS, bin_size, clip_starts=_starts(lengths))
    assert isinstance(layout, ClipLayout)
    starts = _starts(lengths)
    # clip c has ceil(T_c / b) time bins (or the released count), indexed clip by clip
    for c, n in enumerate(lengths):
        expected = (math.ceil(round(n / FPS / bin_size, 9)) if kind == "time" else int(n // FPS) + 1)
        # a sliver bin shorter than a frame holds no frame and is dropped (bins.py)
        assert int(layout.clip_num_bins[c]) in (expected, expected - 1)
    assert int(layout.clip_num_bins.sum()) == layout.num_bins
    # global bin -> (clip, frame range): every frame of the range is in the clip and maps back to the bin
    for b in range(layout.num_bins):
        c = int(layout.bin_clip[b])
        first, count = int(layout.bin_first_frame[b]), int(layout.bin_num_frames[b])
        assert starts[c] <= first and first + count <= starts[c] + lengths[c]
        frames = torch.arange(first, first + count)
        assert bool((layout.frame_to_bin[frames] == b).all())
        assert int(layout.bin_last_in_clip[b]) == int(layout.clip_first_bin[c] + layout.clip_num_bins[c] - 1)
    # (clip, frame) -> global bin: the bin holds that frame and belongs to that clip
    for c, n in enumerate(lengths):
        local = torch.arange(n)
        bins = layout.global_bin(torch.full_like(local, c), local)
        assert bool((layout.bin_clip[bins] == c).all())
        lo, hi = layout.bin_first_frame[bins], layout.bin_first_frame[bins] + layout.bin_num_frames[bins]
        assert bool(((starts[c] + local >= lo) & (starts[c] + local < hi)).all())
    # start frames drawn for a bin stay in its clip (released: in the clip, as the released formula draws)
    g = torch.Generator().manual_seed(0)
    bins = torch.arange(layout.num_bins).repeat(20)
    frames = layout.sample_frames(bins, generator=g)
    clip_of_frame = torch.bucketize(frames, torch.tensor(starts), right=True) - 1
    assert bool((clip_of_frame == layout.bin_clip[bins]).all())
    if kind == "time":
        assert bool((layout.frame_to_bin[frames] == bins).all())
    # edges increase and end at the library's duration
    assert bool((layout.edges_s[1:] > layout.edges_s[:-1]).all())
    assert layout.edges_s[-1].item() == pytest.approx(sum(lengths) / FPS)


def test_a_single_clip_layout_is_the_old_one_with_one_clip():
    layout = make_layout("time", 500, FPS, 1.0, clip_starts=[0], clip_names=["dance"])
    assert type(layout).__name__ == "BinLayout" and layout.num_clips == 1 and layout.clip_names == ("dance",)
    assert layout.bin_clip.tolist() == [0] * 10 and layout.bin_last_in_clip.tolist() == [9] * 10


def test_known_layout_of_two_clips():
    # 2.5 s and 1.2 s at 50 fps, 1 s bins: 3 + 2 bins; clip 2 starts at 2.5 s
    layout = make_layout("time", 185, FPS, 1.0, clip_starts=[0, 125], clip_names=["a", "b"])
    assert layout.num_bins == 5
    assert layout.bin_clip.tolist() == [0, 0, 0, 1, 1]
    assert layout.bin_first_frame.tolist() == [0, 50, 100, 125, 175]
    assert layout.bin_num_frames.tolist() == [50, 50, 25, 50, 10]
    assert layout.edges_s.tolist() == pytest.approx([0, 1, 2, 2.5, 3.5, 3.7])
    assert layout.bin_last_in_clip.tolist() == [2, 2, 2, 4, 4]
    assert "5 time bins of 1 s over 2 clips" in layout.describe()


def _two_clip_layout():
    return make_layout("time", 185, FPS, 1.0, clip_starts=[0, 125], clip_names=["a", "b"])


def test_the_lookahead_kernel_stops_at_the_clip_end():
    layout = _two_clip_layout()
    s = AdaptiveSampler(5, AdaptiveConfig(gamma=0.5, lambda_uniform=0.0, K=3, alpha_smooth=1.0))
    s.set_clips(layout.bin_clip, layout.bin_last_in_clip, 2)
    # only the first bin of clip b fails: clip a's last bin (2) must not see it through the kernel
    s.update_counts(torch.ones(5, dtype=torch.float64), torch.tensor([0, 0, 0, 1, 0], dtype=torch.float64))
    p = s.probabilities()
    assert p[2].item() == 0.0 and p[1].item() == 0.0
    assert p[3].item() == pytest.approx(1.0)
    # without clips the kernel reads across: bin 2 gets gamma/(1+gamma+gamma^2) of bin 3's rate
    t = AdaptiveSampler(5, AdaptiveConfig(gamma=0.5, lambda_uniform=0.0, K=3, alpha_smooth=1.0))
    t.update_counts(torch.ones(5, dtype=torch.float64), torch.tensor([0, 0, 0, 1, 0], dtype=torch.float64))
    assert t.probabilities()[2].item() > 0


def test_clip_balance_known_answers():
    layout = _two_clip_layout()  # 3 bins in clip a, 2 in clip b
    cfg = sampler_config({"name": "uniform", "kind": "uniform", "clip_balance": "clips"})
    u = make_sampler(cfg, 5, layout=layout)
    assert u.probabilities().tolist() == pytest.approx([1 / 6, 1 / 6, 1 / 6, 1 / 4, 1 / 4])
    bins = make_sampler(sampler_config({"name": "uniform", "kind": "uniform"}), 5, layout=layout)
    assert bins.probabilities().tolist() == pytest.approx([0.2] * 5)
    w = make_sampler(cfg, 5, layout=layout, clip_weights=[3.0, 1.0])
    assert w.probabilities().tolist() == pytest.approx([0.25, 0.25, 0.25, 0.125, 0.125])
    # adaptive, K=1, lambda 0: P within a clip follows the rates, each clip gets 1/2
    a = AdaptiveSampler(5, AdaptiveConfig(gamma=0.5, lambda_uniform=0.0, K=1, alpha_smooth=1.0))
    a.set_clips(layout.bin_clip, layout.bin_last_in_clip, 2, "clips")
    # failure rates 1/4, 3/4, 0 in clip a and 1, 0 in clip b (alpha 1: the EMA is the last batch)
    a.update_counts(torch.full((5,), 4.0, dtype=torch.float64), torch.tensor([1, 3, 0, 4, 0], dtype=torch.float64))
    assert a.probabilities().tolist() == pytest.approx([0.125, 0.375, 0.0, 0.5, 0.0])
    # a clip without any failure (zero mass) is uniform within itself
    a.update_counts(torch.ones(5, dtype=torch.float64), torch.tensor([1, 0, 0, 0, 0], dtype=torch.float64))
    assert a.probabilities().tolist() == pytest.approx([0.5, 0.0, 0.0, 0.25, 0.25])
    assert float(a.probabilities().sum()) == pytest.approx(1.0)


@settings(max_examples=40, deadline=None)
@given(lengths=st.lists(st.integers(60, 300), min_size=2, max_size=5), seed=st.integers(0, 10**6),
       weights=st.lists(st.floats(0.1, 10), min_size=5, max_size=5))
def test_clip_balance_gives_each_clip_its_share(lengths, seed, weights):
    layout = make_layout("time", sum(lengths), FPS, 0.5, clip_starts=_starts(lengths))
    w = weights[: len(lengths)]
    s = AdaptiveSampler(layout.num_bins, AdaptiveConfig(gamma=0.9, lambda_uniform=0.1, K=5, alpha_smooth=0.3))
    s.set_clips(layout.bin_clip, layout.bin_last_in_clip, layout.num_clips, "clips", w)
    g = torch.Generator().manual_seed(seed)
    s.update_counts(torch.ones(layout.num_bins, dtype=torch.float64),
                    (torch.rand(layout.num_bins, generator=g) < 0.3).double())
    p = s.probabilities()
    assert bool((p >= 0).all()) and float(p.sum()) == pytest.approx(1.0)
    mass = torch.zeros(layout.num_clips, dtype=torch.float64).index_add_(0, layout.bin_clip, p)
    assert mass.tolist() == pytest.approx([x / sum(w) for x in w])


def test_bad_clip_weights_are_refused_in_one_line():
    layout = _two_clip_layout()
    with pytest.raises(Exception, match="clip weights must be 2 finite numbers > 0"):
        UniformSampler(5).set_clips(layout.bin_clip, layout.bin_last_in_clip, 2, "clips", [1.0, -1.0])


def test_clip_balance_is_a_checked_key():
    from bmimic.sampling.config import validate_sampler_config

    with pytest.raises(Exception, match="clip_balance"):
        validate_sampler_config({"name": "uniform", "kind": "uniform", "clip_balance": "motions"})


@pytest.mark.parametrize("attribution", ["start", "failure"])
def test_an_episode_across_a_clip_end_is_charged_to_the_right_clip_and_bin(attribution):
    from bmimic.sampling.feedback import SamplerFeedback

    layout = _two_clip_layout()  # clip a: frames 0-124, bins 0-2; clip b: frames 125-184, bins 3-4
    acc = SamplerFeedback(UniformSampler(5), layout, num_envs=2, max_episode_length=500, attribution=attribution)
    no = torch.zeros(2, dtype=torch.bool)
    acc.start_episodes(torch.tensor([True, True]), torch.tensor([1, 0]))  # env 0 starts at frame 60, bin 1
    # step k: env 0 reaches clip a's last frame (124) and is resampled into clip b, the episode goes on
    at_clip_end = acc.count(dones=no, clip_end=torch.tensor([True, False]), end_frames=torch.tensor([124, 0]),
                            segment_start=torch.tensor([60, 0]), terminated=no, broken=no,
                            episode_length=torch.tensor([65, 65]))
    # later: env 0 falls at frame 182 (bin 4, clip b) after 70 steps, a short episode: a failure
    at_fall = acc.count(dones=torch.tensor([True, False]), clip_end=no, end_frames=torch.tensor([182, 0]),
                        segment_start=torch.tensor([180, 0]), terminated=torch.tensor([True, False]), broken=no,
                        episode_length=torch.tensor([70, 70]))
    total = at_clip_end + at_fall
    if attribution == "start":  # one episode, charged to its start bin (clip a) through the resample
        assert total[0].tolist() == [0, 1, 0, 0, 0] and total[1].tolist() == [0, 1, 0, 0, 0]
    else:  # visits where the reference ran (bins 1, 2 of clip a; bin 4 of clip b), the failure where it fell
        assert total[0].tolist() == [0, 1, 1, 0, 1] and total[1].tolist() == [0, 0, 0, 0, 1]
        assert layout.clip_names[int(layout.bin_clip[4])] == "b"
