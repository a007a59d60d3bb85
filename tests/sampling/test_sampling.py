"""Tests of bmimic.sampling: bins and layouts, the samplers, episode accounting, config and the named
variants, diagnostics."""

from __future__ import annotations

import dataclasses
import inspect
import io
import math
import random

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from bmimic.sampling import (
    SAMPLERS,
    AccountingConfig,
    AdaptiveConfig,
    AdaptiveSampler,
    BeyondMimicConfig,
    BeyondMimicSampler,
    BinLayout,
    ReleasedBinLayout,
    SamplerConfigError,
    SamplerFeedback,
    UniformConfig,
    UniformSampler,
    attribute,
    bin_edges_s,
    bin_table,
    bins_of_time,
    failed_mask,
    layout_for,
    load_variant,
    make_layout,
    make_sampler,
    num_bins,
    summary,
    validate_sampler_config,
    variant_names,
    visits_histogram,
)
from bmimic.sampling.config import describe, sampler_config
from bmimic.sampling.diagnostics import BIN_TABLE_COLUMNS, MAX_SAMPLER_ROWS, log_every

T = True
F = False


# --- plain-Python references of the formulas (loops, no torch) -------------------------------


def _kernel_smooth(x, gamma, K):
    S = len(x)
    norm = sum(gamma**u for u in range(K))
    return [sum(gamma**u * x[min(s + u, S - 1)] for u in range(K)) / norm for s in range(S)]


def ref_adaptive(S, gamma, lambda_uniform, K, alpha_smooth, batches, empty_bins="decay"):
    """batches: list of (bins, failed) lists, one per update. Returns (r, P).

    raw_s = f_s / max(n_s, 1); r <- alpha raw + (1 - alpha) r for every bin ("decay") or only
    for bins with n_s > 0 ("hold")."""
    r = [0.0] * S
    for bins, failed in batches:
        n = [0] * S
        f = [0] * S
        for b, x in zip(bins, failed, strict=True):
            n[b] += 1
            f[b] += int(x)
        for s in range(S):
            if n[s] > 0 or empty_bins == "decay":
                r[s] = alpha_smooth * f[s] / max(n[s], 1) + (1 - alpha_smooth) * r[s]
    c = _kernel_smooth(r, gamma, K)
    total = sum(c)
    p = [ci / total for ci in c] if total > 0 else [1.0 / S] * S
    return r, [lambda_uniform / S + (1 - lambda_uniform) * pi for pi in p]


def ref_beyondmimic(S, gamma, K, alpha, uniform_ratio, batches, empty_bins="decay"):
    """batches: list of (bins, failed) lists (possibly empty). Returns (q, P)."""
    q = [0.0] * S
    for bins, failed in batches:
        h = [0] * S
        n = [0] * S
        for b, x in zip(bins, failed, strict=True):
            h[b] += int(x)
            n[b] += 1
        q = [alpha * h[s] + (1 - alpha) * q[s] if n[s] > 0 or empty_bins == "decay" else q[s] for s in range(S)]
    w = _kernel_smooth([qs + uniform_ratio / S for qs in q], gamma, K)
    total = sum(w)
    return q, [wi / total for wi in w]


def _random_batches(rng, S, num_batches, max_n):
    """Per-iteration batches; each draws its bins from a random subset, so many bins are empty."""
    out = []
    for _ in range(num_batches):
        n = rng.randint(0, max_n)
        live = rng.sample(range(S), rng.randint(1, S))
        out.append(([rng.choice(live) for _ in range(n)], [rng.random() < 0.4 for _ in range(n)]))
    return out


def _feed(sampler, batches):
    for bins, failed in batches:
        sampler.update(torch.tensor(bins, dtype=torch.long), torch.tensor(failed, dtype=torch.bool))


# --- samplers: known answers and references ---------------------------------------------------


@pytest.mark.parametrize(
    "empty_bins,r2,P2",
    [
        # The design: bins 0 and 2 of the second batch have no episodes; every rate moves, so
        # bin 1's decays (0.25 -> 0.125).
        ("decay", [0, 0.125, 0.5, 0.25], [0.084783, 0.258696, 0.397826, 0.258696]),
        # Bins without episodes keep their rate.
        ("hold", [0, 0.25, 0.5, 0.25], [0.111538, 0.296154, 0.357692, 0.234615]),
    ],
)
def test_adaptive_worked_examples(empty_bins, r2, P2):
    s = AdaptiveSampler(4, AdaptiveConfig(gamma=0.5, lambda_uniform=0.2, K=2, alpha_smooth=0.5,
                                          empty_bins=empty_bins))
    s.update(torch.tensor([0, 1, 1, 3]), torch.tensor([F, T, F, T]))
    assert torch.allclose(s.smoothed_failure(), torch.tensor([0, 0.25, 0, 0.5], dtype=torch.float64))
    expected = torch.tensor([0.122727, 0.195455, 0.195455, 0.486364], dtype=torch.float64)
    assert torch.allclose(s.probabilities(), expected, atol=1e-6)
    s.update(torch.tensor([2, 2, 3]), torch.tensor([T, T, F]))
    assert torch.allclose(s.smoothed_failure(), torch.tensor(r2, dtype=torch.float64))
    assert torch.allclose(s.probabilities(), torch.tensor(P2, dtype=torch.float64), atol=1e-6)


def test_beyondmimic_hand_example():
    # S=3, K=2, gamma=0.5 -> kernel [2/3, 1/3]; alpha=0.5, uniform_ratio=0.3 -> +0.1 per bin.
    s = BeyondMimicSampler(3, BeyondMimicConfig(gamma=0.5, K=2, alpha=0.5, uniform_ratio=0.3))
    s.update(torch.tensor([2, 2, 0]), torch.tensor([T, T, F]))  # h = [0, 0, 2] -> q = [0, 0, 1]
    assert torch.allclose(s.smoothed_failure(), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    w = torch.tensor([0.1, 0.1 * 2 / 3 + 1.1 / 3, 1.1], dtype=torch.float64)
    assert torch.allclose(s.probabilities(), w / w.sum(), atol=1e-12)
    # An empty update still decays q: q = [0, 0, 0.5].
    s.update(torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.bool))
    assert torch.allclose(s.smoothed_failure(), torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64))
    w = torch.tensor([0.1, 0.1 * 2 / 3 + 0.6 / 3, 0.6], dtype=torch.float64)
    assert torch.allclose(s.probabilities(), w / w.sum(), atol=1e-12)


def test_initial_distributions_are_uniform():
    for s in (UniformSampler(7), AdaptiveSampler(7), BeyondMimicSampler(7, BeyondMimicConfig(K=3))):
        assert torch.allclose(s.probabilities(), torch.full((7,), 1 / 7, dtype=torch.float64))


def test_uniform_ignores_updates():
    s = UniformSampler(5)
    s.update(torch.tensor([0, 0, 1]), torch.tensor([T, T, T]))
    assert torch.allclose(s.probabilities(), torch.full((5,), 0.2, dtype=torch.float64))
    assert torch.isnan(s.smoothed_failure()).all()


@pytest.mark.parametrize("empty_bins", ["decay", "hold"])
@pytest.mark.parametrize("seed", range(8))
def test_adaptive_matches_reference(seed, empty_bins):
    rng = random.Random(seed)
    S, K = rng.randint(1, 40), rng.randint(1, 8)
    gamma, lam, a = rng.uniform(0.05, 1.0), rng.uniform(0.0, 1.0), rng.uniform(0.01, 1.0)
    batches = _random_batches(rng, S, rng.randint(1, 25), 30)
    s = AdaptiveSampler(S, AdaptiveConfig(gamma=gamma, lambda_uniform=lam, K=K, alpha_smooth=a,
                                          empty_bins=empty_bins))
    _feed(s, batches)
    r, P = ref_adaptive(S, gamma, lam, K, a, batches, empty_bins)
    assert np.allclose(s.smoothed_failure().numpy(), r, rtol=0, atol=1e-12)
    assert np.allclose(s.probabilities().numpy(), P, rtol=0, atol=1e-12)


@pytest.mark.parametrize("empty_bins", ["decay", "hold"])
@pytest.mark.parametrize("seed", range(8))
def test_beyondmimic_matches_reference(seed, empty_bins):
    rng = random.Random(100 + seed)
    S, K = rng.randint(1, 40), rng.randint(1, 8)
    gamma, a, eps = rng.uniform(0.05, 1.0), rng.uniform(0.001, 1.0), rng.uniform(0.01, 5.0)
    batches = _random_batches(rng, S, rng.randint(1, 25), 30)
    s = BeyondMimicSampler(S, BeyondMimicConfig(gamma=gamma, K=K, alpha=a, uniform_ratio=eps,
                                                empty_bins=empty_bins))
    _feed(s, batches)
    q, P = ref_beyondmimic(S, gamma, K, a, eps, batches, empty_bins)
    assert np.allclose(s.smoothed_failure().numpy(), q, rtol=1e-12, atol=1e-12)
    assert np.allclose(s.probabilities().numpy(), P, rtol=0, atol=1e-12)


def test_update_with_visits_uses_visit_counts_as_denominator():
    s = AdaptiveSampler(3, AdaptiveConfig(gamma=0.5, lambda_uniform=0.0, K=1, alpha_smooth=1.0))
    # One failure ending in bin 2; bins 0..2 each visited by 4 segments.
    s.update(torch.tensor([2]), torch.tensor([T]), visits=torch.tensor([4, 4, 4]))
    assert torch.allclose(s.smoothed_failure(), torch.tensor([0.0, 0.0, 0.25], dtype=torch.float64))


def test_update_counts_equals_update():
    bins, failed = torch.tensor([0, 2, 2, 4, 4, 4]), torch.tensor([T, F, T, F, F, T])
    a, b = AdaptiveSampler(5, AdaptiveConfig(K=2)), AdaptiveSampler(5, AdaptiveConfig(K=2))
    a.update(bins, failed)
    b.update_counts(torch.bincount(bins, minlength=5), torch.bincount(bins[failed], minlength=5))
    assert torch.equal(a.probabilities(), b.probabilities())


def test_update_rejects_bad_input():
    s = AdaptiveSampler(4)
    with pytest.raises(SamplerConfigError, match=r"bins must lie in \[0, 4\)"):
        s.update(torch.tensor([0, 4]), torch.tensor([T, F]))
    with pytest.raises(SamplerConfigError, match="equal length"):
        s.update(torch.tensor([0, 1]), torch.tensor([T]))
    with pytest.raises(SamplerConfigError, match="integer tensor"):
        s.update(torch.tensor([0.5]), torch.tensor([T]))
    with pytest.raises(SamplerConfigError, match=r"episodes must have shape \(4,\)"):
        s.update_counts(torch.zeros(3), torch.zeros(4))


def test_zero_probability_bins_are_never_sampled():
    # lambda_uniform = 0 and K = 1: only bins with a non-zero failure rate have mass.
    for method in ("inverse_cdf", "multinomial"):
        s = AdaptiveSampler(6, AdaptiveConfig(lambda_uniform=0.0, K=1, alpha_smooth=1.0), method=method)
        s.update(torch.tensor([1, 4]), torch.tensor([T, T]))
        drawn = s.sample(20000, generator=torch.Generator().manual_seed(0))
        assert set(drawn.unique().tolist()) == {1, 4}


# --- properties -------------------------------------------------------------------------------

_batch = st.lists(st.tuples(st.integers(0, 10**6), st.booleans()), max_size=40)


@settings(max_examples=60, deadline=None)
@given(
    S=st.integers(1, 50),
    K=st.integers(1, 10),
    gamma=st.floats(1e-3, 1.0),
    lam=st.floats(0.0, 1.0),
    a=st.floats(1e-4, 1.0),
    batches=st.lists(_batch, max_size=6),
)
def test_adaptive_properties(S, K, gamma, lam, a, batches):
    s = AdaptiveSampler(S, AdaptiveConfig(gamma=gamma, lambda_uniform=lam, K=K, alpha_smooth=a))
    for batch in batches:
        s.update(
            torch.tensor([b % S for b, _ in batch], dtype=torch.long), torch.tensor([x for _, x in batch])
        )
        p = s.probabilities()
        assert torch.isfinite(p).all()
        assert (p >= 0).all()
        assert abs(float(p.sum()) - 1.0) < 1e-9
        assert (p >= lam / S - 1e-6).all()
        r = s.smoothed_failure()
        assert ((r >= 0) & (r <= 1)).all()


@settings(max_examples=60, deadline=None)
@given(
    S=st.integers(1, 50),
    K=st.integers(1, 10),
    gamma=st.floats(1e-3, 1.0),
    a=st.floats(1e-4, 1.0),
    eps=st.floats(1e-6, 100.0),
    counts=st.lists(st.lists(st.integers(0, 10**6), min_size=50, max_size=50), max_size=6),
)
def test_beyondmimic_properties(S, K, gamma, a, eps, counts):
    s = BeyondMimicSampler(S, BeyondMimicConfig(gamma=gamma, K=K, alpha=a, uniform_ratio=eps))
    for c in counts:
        failures = torch.tensor(c[:S], dtype=torch.float64)
        s.update_counts(failures, failures)
        p = s.probabilities()
        assert torch.isfinite(p).all()
        assert (p > 0).all()
        assert abs(float(p.sum()) - 1.0) < 1e-9


def test_stress_long_motion_many_updates_no_drift():
    # A 240 s motion at 1 s bins; 10^4 sequential updates with extreme inputs. (The benchmark,
    # `python -m bmimic.sampling.benchmark --iters 1000000`, runs 10^6.)
    S, n = 240, 10_000
    layout = BinLayout(240 * 50, 50.0, 1.0)
    assert layout.num_bins == S
    ad = AdaptiveSampler(S, AdaptiveConfig(gamma=0.8, lambda_uniform=0.1, K=5, alpha_smooth=0.001))
    bm = BeyondMimicSampler(S, BeyondMimicConfig(gamma=0.8, K=3, alpha=0.001, uniform_ratio=0.1))
    huge = torch.full((S,), 1e9, dtype=torch.float64)
    zeros = torch.zeros(S, dtype=torch.float64)
    # Extreme batches first: enormous counts, all failing, then nothing at all.
    for _ in range(100):
        ad.update_counts(huge, huge)
        bm.update_counts(huge, huge)
        ad.update_counts(zeros, zeros)
        bm.update_counts(zeros, zeros)
    for s in (ad, bm):
        p = s.probabilities()
        assert torch.isfinite(p).all() and abs(float(p.sum()) - 1) < 1e-9
    # Then a constant input: the EMAs must follow the closed form x (1 - (1 - a)^k) from a known
    # start, i.e. no accumulated rounding drift.
    ad.load_state_dict({**ad.state_dict(), "state": {"rate": zeros.clone()}})
    bm.load_state_dict({**bm.state_dict(), "state": {"count": zeros.clone()}})
    episodes = torch.full((S,), 3.0, dtype=torch.float64)
    failures = torch.arange(S, dtype=torch.float64) % 4  # rates 0, 1/3, 2/3, 1
    for _ in range(n):
        ad.update_counts(episodes, failures)
        bm.update_counts(episodes, failures)
    decay = 1 - (1 - 0.001) ** n
    assert torch.allclose(ad.smoothed_failure(), failures / 3 * decay, rtol=1e-9, atol=1e-12)
    assert torch.allclose(bm.smoothed_failure(), failures * decay, rtol=1e-9, atol=1e-12)
    for s in (ad, bm):
        p = s.probabilities()
        assert torch.isfinite(p).all() and (p > 0).all() and abs(float(p.sum()) - 1) < 1e-9
    assert (ad.probabilities() >= 0.1 / S - 1e-12).all()


# --- sampling, state ----------------------------------------------------------------------------


def _fresh(kind, S=20):
    if kind == "uniform":
        return UniformSampler(S)
    if kind == "adaptive":
        return AdaptiveSampler(S, AdaptiveConfig(K=3))
    return BeyondMimicSampler(S, BeyondMimicConfig(K=3, alpha=0.05))


def _trained(kind, S=20):
    g = torch.Generator().manual_seed(3)
    s = _fresh(kind, S)
    for _ in range(30):
        bins = torch.randint(0, S, (16,), generator=g)
        s.update(bins, torch.rand(16, generator=g) < bins.double() / S)
    return s


@pytest.mark.parametrize("kind", ["adaptive", "beyondmimic"])
@pytest.mark.parametrize("method", ["inverse_cdf", "multinomial"])
def test_sampling_frequencies_match_probabilities(kind, method):
    s = _trained(kind)
    s.method = method
    n = 200_000
    drawn = s.sample(n, generator=torch.Generator().manual_seed(1234))
    assert drawn.dtype == torch.long and drawn.shape == (n,)
    observed = torch.bincount(drawn, minlength=s.num_bins).numpy()
    expected = s.probabilities().numpy() * n
    assert stats.chisquare(observed, expected).pvalue > 1e-3


@pytest.mark.parametrize("kind", ["uniform", "adaptive", "beyondmimic"])
def test_state_dict_round_trip(kind):
    s = _trained(kind)
    buf = io.BytesIO()
    torch.save(s.state_dict(), buf)
    buf.seek(0)
    restored = _fresh(kind)
    restored.load_state_dict(torch.load(buf))
    assert torch.equal(restored.probabilities(), s.probabilities())
    a = s.sample(1000, generator=torch.Generator().manual_seed(7))
    b = restored.sample(1000, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b)
    # Further updates stay in lock-step.
    s.update(torch.tensor([1, 2]), torch.tensor([T, F]))
    restored.update(torch.tensor([1, 2]), torch.tensor([T, F]))
    assert torch.equal(restored.probabilities(), s.probabilities())


def test_load_state_dict_rejects_mismatch():
    with pytest.raises(SamplerConfigError, match="'adaptive' sampler with 20 bins"):
        BeyondMimicSampler(20).load_state_dict(AdaptiveSampler(20).state_dict())
    with pytest.raises(SamplerConfigError, match="with 21 bins"):
        AdaptiveSampler(20).load_state_dict(AdaptiveSampler(21).state_dict())


def test_probabilities_are_a_copy():
    s = AdaptiveSampler(4)
    s.probabilities().zero_()
    assert abs(float(s.probabilities().sum()) - 1) < 1e-12


# --- bins -----------------------------------------------------------------------------------------


def test_num_bins_and_edges():
    assert num_bins(30.0, 1.0) == 30
    assert num_bins(30.5, 1.0) == 31
    assert num_bins(1.1, 0.1) == 11  # 1.1 / 0.1 == 11.000000000000002
    assert num_bins(0.7, 0.1) == 7  # 0.7 / 0.1 == 6.999999999999999
    assert num_bins(2.0, 2.0) == 1
    assert torch.allclose(bin_edges_s(2.5, 1.0), torch.tensor([0.0, 1.0, 2.0, 2.5], dtype=torch.float64))
    assert len(bin_edges_s(30.0, 1.0)) == 31


def test_layout_regular_and_last_shorter_bin():
    lay = BinLayout(1500, 50.0, 1.0)
    assert lay.num_bins == 30 and lay.duration_s == 30.0
    assert torch.equal(lay.bin_num_frames, torch.full((30,), 50))
    assert torch.equal(lay.bin_first_frame, torch.arange(30) * 50)
    lay = BinLayout(1525, 50.0, 1.0)  # 30.5 s
    assert lay.num_bins == 31 and int(lay.bin_num_frames[-1]) == 25
    assert float(lay.edges_s[-1]) == 30.5
    # The frame at time T (frame N) and time T itself are in the last bin.
    assert int(lay.bins_of(torch.tensor([1525]))[0]) == 30
    assert int(bins_of_time(torch.tensor([30.5]), 1.0, 31)[0]) == 30
    assert lay.bins_of(torch.tensor([0, 49, 50, 1499, 1500, 1524])).tolist() == [0, 0, 1, 29, 30, 30]


def test_layout_float_precision():
    lay = BinLayout(30, 30.0, 0.1)  # 3 frames per bin; 9/30/0.1 == 2.9999999999999996
    assert lay.num_bins == 10
    assert lay.frame_to_bin.tolist() == [i // 3 for i in range(30)]
    lay = BinLayout(33, 30.0, 0.1)
    assert lay.num_bins == 11 and lay.frame_to_bin.tolist() == [i // 3 for i in range(33)]


def test_layout_drops_frameless_sliver_bin():
    # 10 frames at 1 fps, 3.2 s bins: ceil(10/3.2) = 4 bins but the 4th, [9.6, 10) s, holds no frame.
    assert num_bins(10.0, 3.2) == 4
    lay = BinLayout(10, 1.0, 3.2)
    assert lay.num_bins == 3
    assert lay.frame_to_bin.tolist() == [0, 0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert torch.allclose(lay.edges_s, torch.tensor([0.0, 3.2, 6.4, 10.0], dtype=torch.float64))
    assert (lay.bin_num_frames >= 1).all()


def test_layout_rejects_bad_bin_size():
    with pytest.raises(SamplerConfigError, match="sampler.bin_size_seconds must be a finite number > 0"):
        BinLayout(100, 50.0, 0.0)
    with pytest.raises(SamplerConfigError, match=r"<= the motion duration \(2 s\)"):
        BinLayout(100, 50.0, 2.5)
    with pytest.raises(SamplerConfigError, match="at least one frame period"):
        BinLayout(100, 50.0, 0.01)


@pytest.mark.parametrize("T,B", [(1500, 31), (1501, 31), (6574, 132)])
def test_released_layout_matches_the_released_formulas(T, B):
    """B = T // (1 / (decimation * dt)) + 1; failure bin floor(t B / T); start floor((b + U) / B (T - 1))."""
    lay = ReleasedBinLayout(T, 50.0)
    assert lay.num_bins == B == int(T // (1 / (4 * 0.005))) + 1
    t = list(range(T + 1))  # frame T (past the end) as well
    assert lay.bins_of(torch.tensor(t)).tolist() == [min(max(x * B // max(T, 1), 0), B - 1) for x in t]
    bins = torch.randint(0, B, (20_000,), generator=torch.Generator().manual_seed(T))
    frames = lay.sample_frames(bins, generator=torch.Generator().manual_seed(1))
    u = torch.rand(20_000, generator=torch.Generator().manual_seed(1), dtype=torch.float64).tolist()
    assert frames.tolist() == [math.floor((b + x) / B * (T - 1)) for b, x in zip(bins.tolist(), u, strict=True)]
    assert 0 <= int(frames.min()) and int(frames.max()) <= T - 2
    # The T vs T-1 mismatch of the released code: a start drawn for bin b lies in bin b or b-1.
    assert set((bins - lay.bins_of(frames)).tolist()) == {0, 1}
    # The tables the diagnostics and the evaluation read follow the frame -> bin map.
    assert int(lay.bin_num_frames.sum()) == T and (lay.bin_num_frames >= 1).all()
    assert torch.equal(lay.bins_of(lay.bin_first_frame), torch.arange(B))
    assert torch.equal(lay.bins_of(lay.bin_first_frame - 1)[1:], torch.arange(B - 1))
    assert float(lay.edges_s[-1]) == T / 50.0
    assert torch.allclose(lay.edges_s[:-1], lay.bin_first_frame.double() / 50.0)


def test_make_layout_picks_the_layout():
    assert isinstance(make_layout("time", 1500, 50.0, 1.0), BinLayout)
    released = make_layout("released", 1500, 50.0, None)
    assert isinstance(released, ReleasedBinLayout) and released.num_bins == 31
    assert layout_for(load_variant("beyondmimic"), 1500, 50.0).num_bins == 31
    assert layout_for(load_variant("adaptive"), 1500, 50.0).num_bins == 30
    with pytest.raises(SamplerConfigError, match="sampler.bins must be one of time, released, got 'frames'"):
        make_layout("frames", 1500, 50.0, 1.0)


def test_sample_frames_uniform_within_bin():
    lay = BinLayout(1525, 50.0, 1.0)
    g = torch.Generator().manual_seed(0)
    bins = torch.randint(0, lay.num_bins, (100_000,), generator=g)
    frames = lay.sample_frames(bins, generator=g)
    assert torch.equal(lay.bins_of(frames), bins)
    # Within the short last bin every one of its 25 frames is drawn about equally often.
    last = frames[bins == 30] - 1500
    counts = torch.bincount(last, minlength=25).numpy()
    assert len(counts) == 25 and stats.chisquare(counts).pvalue > 1e-3


def _visits_ref(starts, ends, S):
    out = [0] * S
    for a, b in zip(starts, ends, strict=True):
        for s in range(a, b + 1):
            out[s] += 1
    return out


@settings(max_examples=50, deadline=None)
@given(S=st.integers(1, 30), data=st.data())
def test_visits_histogram_matches_loops(S, data):
    pairs = data.draw(st.lists(st.tuples(st.integers(0, S - 1), st.integers(0, S - 1)), max_size=40))
    starts = [min(p) for p in pairs]
    ends = [max(p) for p in pairs]
    got = visits_histogram(torch.tensor(starts, dtype=torch.long), torch.tensor(ends, dtype=torch.long), S)
    assert got.tolist() == _visits_ref(starts, ends, S)


def test_attribute_both_modes_match_loops():
    lay = BinLayout(500, 50.0, 1.0)  # 10 bins of 50 frames
    g = torch.Generator().manual_seed(5)
    start = torch.randint(0, 500, (300,), generator=g)
    end = torch.minimum(start + torch.randint(0, 200, (300,), generator=g), torch.tensor(499))
    failed = torch.rand(300, generator=g) < 0.3
    sb, eb = (start // 50).tolist(), (end // 50).tolist()
    episodes, failures = attribute(start, end, failed, lay, "failure")
    assert episodes.tolist() == _visits_ref(sb, eb, 10)
    fref = [0] * 10
    for b, x in zip(eb, failed.tolist(), strict=True):
        fref[b] += x
    assert failures.tolist() == fref
    episodes, failures = attribute(start, end, failed, lay, "start")
    assert episodes.tolist() == np.bincount(sb, minlength=10).tolist()
    fref = [0] * 10
    for b, x in zip(sb, failed.tolist(), strict=True):
        fref[b] += x
    assert failures.tolist() == fref
    # `counted` drops segments: the same as passing only the counted ones.
    counted = torch.rand(300, generator=g) < 0.5
    for mode in ("failure", "start"):
        got = attribute(start, end, failed, lay, mode, counted=counted)
        want = attribute(start[counted], end[counted], failed[counted], lay, mode)
        assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    with pytest.raises(SamplerConfigError, match="sampler.accounting.attribution must be one of failure, start"):
        attribute(start, end, failed, lay, "end")


def test_failed_mask():
    terminated = torch.tensor([T, F, T, F])
    length = torch.tensor([10, 100, 90, 79])
    assert failed_mask(terminated, length, 100, "terminated").tolist() == [T, F, T, F]
    # "short" = terminated before 0.8 x max; env 3 is short but ended without a termination
    # (a segment cut by the clip end), so it did not fail.
    assert failed_mask(terminated, length, 100, "short", 0.8).tolist() == [T, F, F, F]
    per_env_max = torch.tensor([10, 200, 100, 80])
    assert failed_mask(terminated, length, per_env_max, "short", 1.0).tolist() == [F, F, T, F]
    with pytest.raises(SamplerConfigError, match="sampler.accounting.failure must be one of"):
        failed_mask(terminated, length, 100, "fell")


# --- episode accounting -----------------------------------------------------------------------------


def _accounting(update_every="iteration", attribution="start", failure="short", sampler=None, num_envs=4):
    layout = BinLayout(50, 5.0, 1.0)  # 10 bins of 5 frames
    sampler = sampler or AdaptiveSampler(10, AdaptiveConfig(K=1, alpha_smooth=0.5, lambda_uniform=0.0))
    acc = SamplerFeedback(sampler, layout, num_envs, max_episode_length=100, attribution=attribution,
                            failure=failure, failure_threshold=0.8, update_every=update_every)
    return acc, layout, sampler


def _b(*xs):
    return torch.tensor(xs, dtype=torch.bool)


def _l(*xs):
    return torch.tensor(xs, dtype=torch.long)


def test_accounting_start_attribution_and_failure_rules():
    acc, layout, _ = _accounting()
    acc.start_episodes(_b(T, T, T, T), _l(1, 1, 4, 7))
    acc.start_episodes(_b(F, T, F, F), _l(0, 9, 0, 0))  # env 1 starts a new episode in bin 9
    # Env 0 terminates after 10 steps (< 0.8 x 100: a failure), env 1 after 90 (not short: an
    # episode, no failure), env 2 times out (never a failure), env 3 goes on (not counted).
    dones, terminated, length = _b(T, T, T, F), _b(T, T, F, F), _l(10, 90, 100, 5)
    frames = _l(33, 20, 12, 40)  # where the segments are now: irrelevant to start attribution
    counts = acc.count(dones, _b(F, F, F, T), frames, frames, terminated, _b(F, F, F, F), length)
    assert counts.dtype == torch.float64 and counts.shape == (2, 10)
    assert counts[0].tolist() == [0, 1, 0, 0, 1, 0, 0, 0, 0, 1]
    assert counts[1].tolist() == [0, 1, 0, 0, 0, 0, 0, 0, 0, 0]
    acc.failure = "terminated"  # any termination fails: env 1 too
    counts = acc.count(dones, _b(F, F, F, F), frames, frames, terminated, _b(F, F, F, F), length)
    assert counts[1].tolist() == [0, 1, 0, 0, 0, 0, 0, 0, 0, 1]
    # A world that broke (here env 1, 90 steps: not short) is a failure whatever the rule says of its
    # length (issue 36: it was never counted, so a bin that blew the simulation up looked mastered).
    acc.failure = "short"
    counts = acc.count(dones, _b(F, F, F, F), frames, frames, _b(F, F, F, F), _b(F, T, F, F), length)
    assert counts[0].tolist() == [0, 1, 0, 0, 1, 0, 0, 0, 0, 1]
    assert counts[1].tolist() == [0, 0, 0, 0, 0, 0, 0, 0, 0, 1]


def test_accounting_failure_attribution_counts_segments():
    acc, layout, _ = _accounting(attribution="failure", failure="terminated")
    acc.start_episodes(_b(T, T, T, T), _l(9, 9, 9, 9))  # start bins are not used here
    seg_start, end = _l(3, 12, 40, 0), _l(14, 12, 49, 4)  # bins [0, 2], [2, 2], [8, 9], [0, 0]
    # env 0 terminates, env 1 times out, env 2's clip ends (it goes on), env 3 continues (not counted)
    counts = acc.count(_b(T, T, F, F), _b(F, F, T, F), end, seg_start, _b(T, F, F, F), _b(F, F, F, F),
                       _l(5, 100, 50, 5))
    assert counts[0].tolist() == [1, 1, 2, 0, 0, 0, 0, 0, 1, 1]
    assert counts[1].tolist() == [0, 0, 1, 0, 0, 0, 0, 0, 0, 0]
    # env 1's world broke instead of timing out: a failure where it broke (bin 2)
    counts = acc.count(_b(T, T, F, F), _b(F, F, T, F), end, seg_start, _b(T, F, F, F), _b(F, T, F, F),
                       _l(5, 100, 50, 5))
    assert counts[0].tolist() == [1, 1, 2, 0, 0, 0, 0, 0, 1, 1]
    assert counts[1].tolist() == [0, 0, 2, 0, 0, 0, 0, 0, 0, 0]


@pytest.mark.parametrize("update_every", ["iteration", "step"])
def test_accounting_update_timing(update_every):
    acc, _, s = _accounting(update_every)
    ref = AdaptiveSampler(10, AdaptiveConfig(K=1, alpha_smooth=0.5, lambda_uniform=0.0))
    c1 = torch.zeros(2, 10, dtype=torch.float64)
    c1[:, 3] = torch.tensor([2.0, 2.0])
    c2 = torch.zeros(2, 10, dtype=torch.float64)
    c2[:, 3] = torch.tensor([2.0, 0.0])
    c2[:, 6] = torch.tensor([1.0, 1.0])
    p0 = s.probabilities()
    acc.record(c1.clone())
    assert torch.equal(s.probabilities(), p0) == (update_every == "iteration")
    acc.record(c2.clone())
    acc.end_rollout()
    if update_every == "iteration":  # one update with the rollout's sum: r_3 = 0.5 * 2/4
        ref.update_counts(c1[0] + c2[0], c1[1] + c2[1])
        assert float(s.smoothed_failure()[3]) == 0.25
    else:  # two updates: r_3 = 0.5 * (0.5 * 1) + 0.5 * 0
        ref.update_counts(c1[0], c1[1])
        ref.update_counts(c2[0], c2[1])
        assert float(s.smoothed_failure()[3]) == 0.25 and float(s.smoothed_failure()[6]) == 0.5
    assert torch.equal(s.probabilities(), ref.probabilities())
    episodes, failures = acc.pop_counts()
    assert episodes.tolist() == (c1[0] + c2[0]).tolist() and failures.tolist() == (c1[1] + c2[1]).tolist()
    assert acc.pop_counts()[0].sum() == 0
    rate = s.smoothed_failure()
    acc.end_rollout()  # iteration: an update without episodes, so every rate decays (the design)
    expected = rate * 0.5 if update_every == "iteration" else rate
    assert torch.equal(s.smoothed_failure(), expected)


@pytest.mark.parametrize("empty_bins", ["decay", "hold"])
@pytest.mark.parametrize("seed", range(4))
def test_accounting_per_iteration_updates_match_reference(seed, empty_bins):
    """Per-step batches through the accounting, one update per iteration, against the plain-Python
    transcription fed one batch per iteration (all the iteration's episodes)."""
    rng = random.Random(1000 + seed)
    S, K, n = 10, rng.randint(1, 6), 16
    gamma, lam, a = rng.uniform(0.1, 1.0), rng.uniform(0.0, 0.5), rng.uniform(0.05, 1.0)
    s = AdaptiveSampler(S, AdaptiveConfig(gamma=gamma, lambda_uniform=lam, K=K, alpha_smooth=a,
                                          empty_bins=empty_bins))
    acc, _, _ = _accounting("iteration", failure="terminated", sampler=s, num_envs=n)
    none = torch.zeros(n, dtype=torch.bool)
    frames, length = torch.zeros(n, dtype=torch.long), torch.full((n,), 5)
    iterations = []
    for _ in range(rng.randint(1, 12)):
        bins, failed = [], []
        for step_bins, step_failed in _random_batches(rng, S, rng.randint(0, 5), n):
            k = len(step_bins)
            acc.start_episodes(~none, torch.tensor(step_bins + [0] * (n - k), dtype=torch.long))
            done = torch.arange(n) < k
            term = done & torch.tensor(step_failed + [False] * (n - k))
            acc.record(acc.count(done, none, frames, frames, term, none, length))
            bins += step_bins
            failed += step_failed
        acc.end_rollout()
        iterations.append((bins, failed))
    r, P = ref_adaptive(S, gamma, lam, K, a, iterations, empty_bins)
    assert np.allclose(s.smoothed_failure().numpy(), r, rtol=0, atol=1e-12)
    assert np.allclose(s.probabilities().numpy(), P, rtol=0, atol=1e-12)


@pytest.mark.parametrize("attribution", ["start", "failure"])
@pytest.mark.parametrize("update_every", ["iteration", "step"])
def test_accounting_step_path_traces_as_one_graph(attribution, update_every):
    """What the environment's captured step calls (start_episodes, count, record) has no graph
    break: no host read, no data-dependent shape (tests/test_env.py checks the whole step for the
    default variant)."""
    import torch._dynamo as dynamo

    acc, layout, s = _accounting(update_every, attribution=attribution,
                                 sampler=BeyondMimicSampler(10, BeyondMimicConfig(K=3)), num_envs=8)
    g = torch.Generator().manual_seed(0)
    done, clip = torch.rand(8, generator=g) < 0.5, torch.rand(8, generator=g) < 0.3
    start = torch.randint(0, 50, (8,), generator=g)
    end, length = torch.clamp(start + 7, max=49), torch.randint(0, 100, (8,), generator=g)

    def step():
        acc.start_episodes(done, s.sample(8))
        acc.record(acc.count(done, clip & ~done, end, start, done & clip, ~done & done, length))

    explained = dynamo.explain(step)()
    assert explained.graph_count == 1 and not explained.break_reasons, explained.break_reasons
    dynamo.reset()


# --- config ---------------------------------------------------------------------------------------


def test_default_config_is_valid_and_factory_builds_each_sampler():
    validate_sampler_config(AdaptiveConfig(), 30.0)
    ad = make_sampler(AdaptiveConfig(gamma=0.5, K=4, lambda_uniform=0.3, alpha_smooth=0.2), 12)
    assert isinstance(ad, AdaptiveSampler)
    assert ad.hparams() == {"gamma": 0.5, "lambda_uniform": 0.3, "K": 4, "alpha_smooth": 0.2, "empty_bins": "decay"}
    bm = make_sampler(BeyondMimicConfig(K=1, alpha=0.01, uniform_ratio=0.2), 12)
    assert isinstance(bm, BeyondMimicSampler) and bm.hparams()["alpha"] == 0.01
    assert isinstance(make_sampler(UniformConfig(), 12), UniformSampler)
    # A plain dict (a run folder's) names its class by `kind`.
    assert isinstance(make_sampler({"name": "x", "kind": "beyondmimic", "K": 2}, 12), BeyondMimicSampler)


DESIGN = {"gamma": 0.9, "lambda_uniform": 0.1, "K": 5, "alpha_smooth": 0.1, "empty_bins": "decay"}
DESIGN_ACCOUNTING = {"attribution": "start", "failure": "short", "failure_threshold": 0.8, "update_every": "iteration"}


def test_adaptive_defaults_are_the_design_from_one_source():
    schema = dataclasses.asdict(AdaptiveConfig())
    assert {k: schema[k] for k in DESIGN} == DESIGN and schema["accounting"] == DESIGN_ACCOUNTING
    assert schema["bins"] == "time" and schema["bin_size_seconds"] == 1.0 and schema["enabled"] is True
    assert dataclasses.asdict(load_variant("adaptive")) == schema  # YAML == schema
    assert AdaptiveSampler(4).hparams() == DESIGN  # built without a config: the schema's defaults
    accounting = inspect.signature(SamplerFeedback).parameters
    for key in DESIGN_ACCOUNTING:
        assert accounting[key].default == schema["accounting"][key], key


def test_the_variants_are_the_yaml_files_of_registered_samplers():
    assert variant_names() == ("adaptive", "adaptive_hybrid", "beyondmimic", "egm", "gmt", "low_return", "phc", "protomotions",
                               "uniform")
    assert {k: (e.cls, e.config) for k, e in SAMPLERS.items() if k in ("adaptive", "beyondmimic", "uniform")} == {
        "adaptive": (AdaptiveSampler, AdaptiveConfig), "beyondmimic": (BeyondMimicSampler, BeyondMimicConfig),
        "uniform": (UniformSampler, UniformConfig)}


@pytest.mark.parametrize("name", variant_names())
def test_each_variant_is_named_after_its_file_and_only_overrides_its_schema(name):
    """A variant selects its schema and sets only keys of it, each to a value other than the schema's
    default (the defaults live in the schema alone)."""
    from omegaconf import OmegaConf

    from tests.conftest import CONF

    cfg = load_variant(name)
    assert cfg.name == name
    validate_sampler_config(cfg, 30.0)
    node = OmegaConf.to_container(OmegaConf.load(CONF / "sampler" / f"{name}.yaml"))
    default = dataclasses.asdict(SAMPLERS[cfg.kind].config())
    assert node.pop("defaults")[0] == f"{cfg.kind}_schema"
    assert set(node) <= set(default) - {"kind"}  # none of another sampler's keys
    assert set(node.get("accounting", {})) <= set(DESIGN_ACCOUNTING)
    for key, value in node.items():
        for k, v in (value.items() if key == "accounting" else [(None, value)]):
            assert v != (default[key][k] if k else default[key]), f"{name}.yaml repeats the default of {key}.{k or ''}"
    layout = layout_for(cfg, 1500, 50.0)
    assert type(make_sampler(cfg, layout.num_bins)) is SAMPLERS[cfg.kind].cls
    assert (CONF / "sampler" / f"{name}.yaml").read_text().startswith("# ")  # a header says what it is


def test_named_variants_are_what_their_names_say():
    hybrid = load_variant("adaptive_hybrid")  # the earlier `adaptive`
    assert dataclasses.asdict(hybrid) == {**dataclasses.asdict(AdaptiveConfig()), "name": "adaptive_hybrid",
                                          "gamma": 0.8, "K": 3, "empty_bins": "hold",
                                          "accounting": {"attribution": "failure", "failure": "terminated",
                                                         "failure_threshold": 0.8, "update_every": "step"}}
    bm = load_variant("beyondmimic")  # the released code, its bins and accounting included
    assert dataclasses.asdict(bm) == {**dataclasses.asdict(BeyondMimicConfig()),
                                      "accounting": {"attribution": "failure", "failure": "terminated",
                                                     "failure_threshold": 0.8, "update_every": "step"}}
    assert (bm.bins, bm.bin_size_seconds, bm.alpha, bm.uniform_ratio) == ("released", None, 0.001, 0.1)
    assert BeyondMimicSampler(4).hparams() == {k: getattr(bm, k) for k in ("gamma", "K", "alpha", "uniform_ratio",
                                                                           "empty_bins")}
    # sampler=uniform has the bins and accounting of sampler=adaptive and no parameters of its own.
    uniform, design = load_variant("uniform"), load_variant("adaptive")
    assert (uniform.bins, uniform.bin_size_seconds, uniform.accounting) == (design.bins, design.bin_size_seconds,
                                                                           design.accounting)


def test_a_flat_sampler_node_of_the_layout_before_the_registry_is_refused_in_one_line():
    """Before the registry every variant held every key flat; bmimic no longer reads that layout (the
    committed results were migrated), and says which key is missing."""
    flat = {"name": "beyondmimic", "enabled": True, "bins": "released", "bin_size_seconds": None, "gamma": 0.8,
            "lambda_uniform": 0.1, "K": 1, "alpha_smooth": 0.1, "empty_bins": "decay", "alpha": 0.001,
            "uniform_ratio": 0.1, "attribution": "failure", "failure": "terminated", "failure_threshold": 0.8,
            "update_every": "step", "log_every": None}
    with pytest.raises(SamplerConfigError, match=r"^sampler\.kind must be one of .*, got None$"):
        validate_sampler_config(flat, 30.0)


def test_disabled_sampler_draws_uniformly_and_says_so():
    cfg = dataclasses.replace(load_variant("adaptive"), enabled=False)
    layout = layout_for(cfg, 1500, 50.0)
    off, uniform = make_sampler(cfg, layout.num_bins), make_sampler(load_variant("uniform"), layout.num_bins)
    assert type(off) is UniformSampler and off.state_dict() == uniform.state_dict()
    off.update(torch.tensor([3, 3]), torch.tensor([T, T]))
    assert torch.equal(off.probabilities(), uniform.probabilities())
    g1, g2 = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
    assert torch.equal(off.sample(100, generator=g1), uniform.sample(100, generator=g2))
    lines = describe(cfg, layout, off)
    assert "sampler.enabled=false" in lines[0] and "uniformly" in lines[0]
    assert not any("enabled" in line for line in describe(load_variant("adaptive"), layout, make_sampler(
        load_variant("adaptive"), layout.num_bins)))


@pytest.mark.parametrize("name", variant_names())
def test_log_names_the_variant_and_every_value_in_force(name):
    cfg = load_variant(name)
    layout = layout_for(cfg, 1500, 50.0)
    sampler = make_sampler(cfg, layout.num_bins)
    text = "\n".join(describe(cfg, layout, sampler))
    assert text.startswith(f"sampler {name} ({type(sampler).__name__})")
    assert f"{layout.num_bins} {'released' if cfg.bins == 'released' else 'time'} bins" in text
    for key, value in sampler.hparams().items():
        assert f"{key}={value}" in text
    for key in ("attribution", "failure", "update_every"):
        assert f"{key}={getattr(cfg.accounting, key)}" in text
    assert ("failure_threshold=0.8" in text) == (cfg.accounting.failure == "short")


def test_bin_size_on_released_bins_is_ignored_with_one_log_line():
    bm = load_variant("beyondmimic")
    layout = layout_for(bm, 1500, 50.0)
    sampler = make_sampler(bm, layout.num_bins)
    assert not any("does not apply" in line for line in describe(bm, layout, sampler))
    bm = dataclasses.replace(bm, bin_size_seconds=0.5)
    validate_sampler_config(bm, 30.0)
    assert layout_for(bm, 1500, 50.0).num_bins == 31
    lines = [line for line in describe(bm, layout, sampler) if "does not apply" in line]
    assert len(lines) == 1 and "sampler.bin_size_seconds=0.5" in lines[0]


@pytest.mark.parametrize("arm,key,value", [
    ("attribution_failure", "accounting.attribution", "failure"),
    ("failure_terminated", "accounting.failure", "terminated"),
    ("update_every_step", "accounting.update_every", "step"),
    ("empty_bins_hold", "empty_bins", "hold"),
])
def test_design_choice_arms_change_one_key_of_the_design(arm, key, value):
    from omegaconf import OmegaConf

    from bmimic.training.resume import flatten_config
    from tests.conftest import compose

    design = OmegaConf.to_object(compose(["+sweep=design_choices"]).sampler)
    assert design == load_variant("adaptive")
    cfg = OmegaConf.to_object(compose(["+sweep=design_choices", f"design_choice={arm}"]).sampler)
    before, after = flatten_config(dataclasses.asdict(design)), flatten_config(dataclasses.asdict(cfg))
    changed = {k for k, v in after.items() if v != before[k]}
    assert changed == {key} and after[key] == value


@pytest.mark.parametrize(
    "cls,key,value,message",
    [
        (AdaptiveConfig, "name", "", "sampler.name must be the variant's name (its file name in conf/sampler/), got ''"),
        (AdaptiveConfig, "enabled", "yes", "sampler.enabled must be true or false, got 'yes'"),
        (AdaptiveConfig, "bins", "frames", "sampler.bins must be one of time, released, got 'frames'"),
        (AdaptiveConfig, "bin_size_seconds", None, "sampler.bin_size_seconds must be a finite number > 0, got None"),
        (AdaptiveConfig, "empty_bins", "keep", "sampler.empty_bins must be one of decay, hold, got 'keep'"),
        (AdaptiveConfig, "log_every", 0, "sampler.log_every must be an integer >= 1 or null, got 0"),
        (AdaptiveConfig, "lambda_uniform", 1.5, "sampler.lambda_uniform must be in [0, 1], got 1.5"),
        (AdaptiveConfig, "lambda_uniform", -0.1, "sampler.lambda_uniform must be in [0, 1], got -0.1"),
        (AdaptiveConfig, "gamma", 0.0, "sampler.gamma must be in (0, 1], got 0.0"),
        (AdaptiveConfig, "gamma", 1.2, "sampler.gamma must be in (0, 1], got 1.2"),
        (AdaptiveConfig, "gamma", math.nan, "sampler.gamma must be in (0, 1], got nan"),
        (AdaptiveConfig, "K", 0, "sampler.K must be an integer >= 1 and <= 1000, got 0"),
        (AdaptiveConfig, "K", 2.5, "sampler.K must be an integer >= 1 and <= 1000, got 2.5"),
        (AdaptiveConfig, "K", 10**9, "sampler.K must be an integer >= 1 and <= 1000, got 1000000000"),  # hung
        (AdaptiveConfig, "alpha_smooth", 0.0, "sampler.alpha_smooth must be in (0, 1], got 0.0"),
        (AdaptiveConfig, "alpha_smooth", 1.01, "sampler.alpha_smooth must be in (0, 1], got 1.01"),
        (BeyondMimicConfig, "alpha", 0.0, "sampler.alpha must be in (0, 1], got 0.0"),
        (BeyondMimicConfig, "alpha", 2.0, "sampler.alpha must be in (0, 1], got 2.0"),
        (BeyondMimicConfig, "uniform_ratio", 0.0, "sampler.uniform_ratio must be a finite number > 0, got 0.0"),
        (BeyondMimicConfig, "K", 0, "sampler.K must be an integer >= 1 and <= 1000, got 0"),
        (UniformConfig, "bin_size_seconds", 0.0, "sampler.bin_size_seconds must be a finite number > 0, got 0.0"),
        (AdaptiveConfig, "bin_size_seconds", -1.0, "sampler.bin_size_seconds must be a finite number > 0, got -1.0"),
        (
            AdaptiveConfig,
            "bin_size_seconds",
            31.0,
            "sampler.bin_size_seconds must be <= the motion duration (30 s), got 31.0",
        ),
    ],
)
def test_validation_errors(cls, key, value, message):
    cfg = cls(**{key: value})
    with pytest.raises(SamplerConfigError) as err:
        validate_sampler_config(cfg, 30.0)
    assert str(err.value) == message


@pytest.mark.parametrize(
    "key,value,message",
    [
        ("update_every", "episode", "sampler.accounting.update_every must be one of iteration, step, got 'episode'"),
        ("attribution", "end", "sampler.accounting.attribution must be one of failure, start, got 'end'"),
        ("failure", "fell", "sampler.accounting.failure must be one of terminated, short, got 'fell'"),
        ("failure_threshold", 0.0, "sampler.accounting.failure_threshold must be in (0, 1], got 0.0"),
        ("failure_threshold", 1.5, "sampler.accounting.failure_threshold must be in (0, 1], got 1.5"),
    ],
)
def test_accounting_validation_errors(key, value, message):
    for cls in (AdaptiveConfig, UniformConfig):
        cfg = cls(accounting=AccountingConfig(**{key: value}))
        with pytest.raises(SamplerConfigError) as err:
            validate_sampler_config(cfg, 30.0)
        assert str(err.value) == message


def test_keys_of_another_sampler_are_refused():
    with pytest.raises(SamplerConfigError, match="sampler.alpha"):
        sampler_config({"name": "adaptive", "kind": "adaptive", "alpha": 0.01})
    with pytest.raises(SamplerConfigError, match="sampler.kind must be one of .*adaptive.*, got .greedy."):
        sampler_config({"name": "x", "kind": "greedy"})


def test_schemas_hold_the_range_rules_and_constructors_the_shape_checks():
    with pytest.raises(SamplerConfigError, match="sampler.lambda_uniform must be in \\[0, 1\\], got 2.0"):
        AdaptiveConfig(lambda_uniform=2.0).check()
    with pytest.raises(SamplerConfigError, match="sampler.K must be an integer >= 1 and <= 1000, got 0"):
        validate_sampler_config(BeyondMimicConfig(K=0))
    with pytest.raises(SamplerConfigError, match="num_bins"):
        UniformSampler(0)


# --- diagnostics ------------------------------------------------------------------------------------


def test_summary_values():
    u = UniformSampler(8)
    d = summary(u, torch.tensor([2, 2, 0, 0, 0, 0, 0, 0]), torch.tensor([1, 0, 0, 0, 0, 0, 0, 0]))
    assert d == {
        "episodes": 4.0,
        "failure_rate": 0.25,
        "sampling_entropy": pytest.approx(1.0),
        "top1_prob": pytest.approx(0.125),
        "top1_bin": 0.0,
    }
    assert summary(UniformSampler(1), torch.zeros(1), torch.zeros(1))["sampling_entropy"] == 1.0
    assert math.isnan(summary(u, torch.zeros(8), torch.zeros(8))["failure_rate"])
    s = AdaptiveSampler(4, AdaptiveConfig(lambda_uniform=0.0, K=1, alpha_smooth=1.0))
    s.update(torch.tensor([2]), torch.tensor([T]))  # all mass on bin 2
    d = summary(s, torch.tensor([0, 0, 5, 0]), torch.tensor([0, 0, 1, 0]), total_episodes=2)
    assert d["sampling_entropy"] == pytest.approx(0.0, abs=1e-12)
    assert d["top1_prob"] == pytest.approx(1.0) and d["top1_bin"] == 2.0
    assert d["episodes"] == 2.0 and d["failure_rate"] == 0.5


def test_bin_table():
    lay = BinLayout(125, 50.0, 1.0)  # 2.5 s -> bins [0,1), [1,2), [2,2.5)
    s = BeyondMimicSampler(3, BeyondMimicConfig(alpha=0.5))
    s.update(torch.tensor([1, 1]), torch.tensor([T, F]))
    df = bin_table(7, lay, torch.tensor([0, 2, 1]), torch.tensor([0, 1, 0]), s)
    assert tuple(df.columns) == BIN_TABLE_COLUMNS
    assert df["iteration"].tolist() == [7, 7, 7] and df["bin"].tolist() == [0, 1, 2]
    assert df["bin_start_s"].tolist() == [0.0, 1.0, 2.0] and df["bin_end_s"].tolist() == [1.0, 2.0, 2.5]
    assert df["episodes"].tolist() == [0, 2, 1] and df["failures"].tolist() == [0, 1, 0]
    assert math.isnan(df["raw_failure_rate"][0]) and df["raw_failure_rate"].tolist()[1:] == [0.5, 0.0]
    assert df["smoothed_failure_rate"].tolist() == [0.0, 0.5, 0.0]
    assert df["probability"].sum() == pytest.approx(1.0)
    df = bin_table(0, lay.edges_s, torch.zeros(3), torch.zeros(3), UniformSampler(3))
    assert df["smoothed_failure_rate"].isna().all()
    with pytest.raises(SamplerConfigError, match="episodes has shape"):
        bin_table(0, lay, torch.zeros(4), torch.zeros(3), UniformSampler(3))


def test_sampler_table_interval():
    assert log_every(None, 30, 10_000) == 1
    assert log_every(None, 1000, 10_000) == 1
    assert log_every(3, 30, 10_000) == 3
    every = log_every(None, 10_000, 10_000)
    assert every == 100
    assert 10_000 * (math.ceil(10_000 / every) + 1) <= 1.01 * MAX_SAMPLER_ROWS  # + the last iteration
    assert log_every(None, 10_000, 50) == 1  # short runs stay complete


# --- GPU: the hot path never synchronises with the host ---------------------------------------------


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_hot_path_has_no_host_sync():
    """Counting, recording, the per-iteration update and sampling, for both layouts and every
    attribution and update schedule, never wait for the device."""
    dev = torch.device("cuda")
    n = 4096
    g = torch.Generator(device=dev).manual_seed(0)
    start = torch.randint(0, 3000, (n,), device=dev, generator=g)
    end = torch.clamp(start + 100, max=2999)
    failed = torch.rand(n, device=dev, generator=g) < 0.2
    done = torch.rand(n, device=dev, generator=g) < 0.1
    length = torch.randint(0, 500, (n,), device=dev, generator=g)
    for lay in (BinLayout(3000, 50.0, 1.0, device=dev), ReleasedBinLayout(3000, 50.0, device=dev)):
        for s in (AdaptiveSampler(lay.num_bins, device=dev),
                  BeyondMimicSampler(lay.num_bins, BeyondMimicConfig(K=3), device=dev)):
            for attribution in ("start", "failure"):
                for update_every in ("iteration", "step"):
                    acc = SamplerFeedback(s, lay, n, 500, attribution=attribution, update_every=update_every,
                                          device=dev)
                    torch.cuda.synchronize()
                    torch.cuda.set_sync_debug_mode("error")
                    try:
                        bins = s.sample(n, generator=g)
                        acc.start_episodes(done, bins)
                        lay.sample_frames(bins, generator=g)
                        acc.record(acc.count(done, ~done, end, start, failed, ~done & done, length))
                        acc.end_rollout()
                    finally:
                        torch.cuda.set_sync_debug_mode("default")
