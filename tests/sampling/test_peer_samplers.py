"""The field's other samplers (EGM, GMT, PHC, ProtoMotions): hand-computed answers of the formulas their
YAML headers and module docs state, properties under random updates, the episode accounting's error
channel, the evaluation hook, their config checks, and 2 CPU iterations of each on the built-in library."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import torch

from bmimic.sampling import EGMSampler, GMTSampler, PHCSampler, ProtoMotionsSampler, SamplerFeedback
from bmimic.sampling.base import ERROR_COMPONENTS
from bmimic.sampling.checks import SamplerConfigError
from bmimic.sampling.config import load_variant, make_sampler, validate_sampler_config
from bmimic.sampling.peer_clips import PHCConfig, ProtoMotionsConfig
from bmimic.sampling.peer_errors import UNSET_SCHEDULE_ITERATIONS, EGMConfig, GMTConfig
from bmimic.sampling.signals import TRACKING_ERRORS
from bmimic.training.clip_rollouts import clips_failed
from tests.conftest import TINY, train_in_process

CLIPS = torch.tensor([0, 0, 0, 1, 1, 2])  # 3 clips of 3, 2 and 1 bins
LAST = torch.tensor([2, 2, 2, 4, 4, 5])
PEERS = ("egm", "gmt", "phc", "protomotions")


def _probs(s) -> np.ndarray:
    return s.probabilities().numpy()


def _errors(pos=(), ori=(), vel=(), worst=(), n=4) -> torch.Tensor:
    rows = [list(r) + [0.0] * (n - len(r)) for r in (pos, ori, vel, worst)]
    return torch.tensor(rows, dtype=torch.float64)


# ---------------------------------------------------------------------------------------------- EGM
def test_egm_known_answer():
    s = EGMSampler(4, EGMConfig(ema=0.5, weight_body_pos=1.0, weight_body_ori=0.1, weight_body_lin_vel=0.1,
                                power_start=2.0, power_end=2.0, uniform_start=0.2, uniform_end=0.2,
                                schedule_iterations=1))
    np.testing.assert_allclose(_probs(s), 0.25)  # no error seen yet: uniform
    # bin 0: body pos 2 m over 2 steps -> 1; bin 1: 20 rad over 1 step x 0.1 -> 2; bins 2, 3 unvisited
    s.update_errors(_errors(pos=[2, 0], ori=[0, 20]), torch.tensor([2.0, 1.0, 0.0, 0.0]))
    # e = [1, 2, 0, 0], e^2 normalised = [0.2, 0.8, 0, 0], P = 0.8 q + 0.2 / 4
    np.testing.assert_allclose(_probs(s), [0.21, 0.69, 0.05, 0.05])
    # bin 0 sees 3: EMA 0.5 -> 2; bin 1 unvisited holds 2
    s.update_errors(_errors(pos=[3]), torch.tensor([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(s.smoothed_failure().numpy(), [2, 2, 0, 0])
    np.testing.assert_allclose(_probs(s), [0.45, 0.45, 0.05, 0.05])


def test_egm_schedule_is_linear_then_constant():
    s = EGMSampler(3, EGMConfig(power_start=0.5, power_end=2.0, uniform_start=0.5, uniform_end=0.1,
                                schedule_iterations=4))
    seen = []
    for _ in range(6):
        tau, u = s.schedule()
        seen.append((float(tau), float(u)))
        s.update_errors(_errors(pos=[1, 2, 3], n=3), torch.ones(3))
    np.testing.assert_allclose(seen, [(0.5, 0.5), (0.875, 0.4), (1.25, 0.3), (1.625, 0.2), (2.0, 0.1), (2.0, 0.1)])
    # at the end: e = [1, 2, 3], p ~ e^2 = [1, 4, 9] / 14, P = 0.9 p + 0.1 / 3
    np.testing.assert_allclose(_probs(s), 0.9 * np.array([1, 4, 9]) / 14 + 0.1 / 3)


# ---------------------------------------------------------------------------------------------- GMT
def test_gmt_known_answer_levels_then_error_at_the_floor():
    s = GMTSampler(4, GMTConfig(subclip_bins=2))  # sub-clips {0, 1} and {2, 3}
    np.testing.assert_allclose(_probs(s), 0.25)  # both at level 10
    s.update_counts(torch.tensor([3.0, 0, 0, 0]), torch.tensor([1.0, 0, 0, 0]))  # 2 completions in sub-clip 0
    c0 = 10 * 0.99**2
    np.testing.assert_allclose(_probs(s), np.array([c0 / 2, c0 / 2, 5, 5]) / (c0 + 10))
    s.update_errors(_errors(worst=[0.3, 0.0]), torch.tensor([2.0, 2.0, 0, 0]))  # E of sub-clip 0: 0.3 / 4 m
    np.testing.assert_allclose(_probs(s), np.array([c0 / 2, c0 / 2, 5, 5]) / (c0 + 10))  # not at the floor yet
    s.update_counts(torch.tensor([1000.0, 0, 0, 0]), torch.zeros(4))  # level floored at 1
    s0 = (0.075 / 0.15) ** 5
    np.testing.assert_allclose(s.smoothed_failure().numpy(), [1, 1, 10, 10])
    np.testing.assert_allclose(_probs(s), np.array([s0 / 2, s0 / 2, 5, 5]) / (s0 + 10))


def test_gmt_subclips_restart_at_every_clip():
    s = GMTSampler(6, GMTConfig(subclip_bins=2))
    s.set_clips(CLIPS, LAST, 3)
    assert s._group.tolist() == [0, 0, 1, 2, 2, 3]
    np.testing.assert_allclose(_probs(s), [1 / 8, 1 / 8, 1 / 4, 1 / 8, 1 / 8, 1 / 4])


# ---------------------------------------------------------------------------------------------- PHC
def test_phc_soft_and_hard_known_answers():
    soft, hard = PHCSampler(6, PHCConfig(mode="soft")), PHCSampler(6, PHCConfig(mode="hard"))
    for s in (soft, hard):
        s.set_clips(CLIPS, LAST, 3)
        np.testing.assert_allclose(_probs(s), [1 / 9] * 3 + [1 / 6] * 2 + [1 / 3])  # every clip alike
        s.observe_eval(torch.tensor([True, False, True]), 10)
        np.testing.assert_allclose(_probs(s), [1 / 6] * 3 + [0, 0] + [1 / 2])  # h = [1, 0, 1]
        s.observe_eval(torch.tensor([True, True, False]), 10)
    np.testing.assert_allclose(_probs(soft), [1 / 6] * 3 + [1 / 8] * 2 + [1 / 4])  # h = [2, 1, 1]
    np.testing.assert_allclose(_probs(hard), [1 / 6] * 3 + [1 / 4] * 2 + [0])  # uniform over the last failed


def test_clip_samplers_on_one_motion_are_uniform():
    for s in (PHCSampler(5), ProtoMotionsSampler(5)):
        s.observe_eval(torch.tensor([True]), 10)
        np.testing.assert_allclose(_probs(s), 0.2)


# ---------------------------------------------------------------------------------------- ProtoMotions
def test_protomotions_known_answer_and_floor():
    s = ProtoMotionsSampler(6)
    s.set_clips(CLIPS, LAST, 3)
    s.observe_eval(torch.tensor([False, True, False]), 200)
    d = 0.999**200
    np.testing.assert_allclose(s._weight[:3].numpy(), [d, 1, d])
    w = np.array([d, 1, d]) / (2 * d + 1)
    np.testing.assert_allclose(_probs(s), [w[0] / 3] * 3 + [w[1] / 2] * 2 + [w[2]])
    for _ in range(20):  # clip 0 keeps succeeding: floored at 1/3; the others fail: reset to 1
        s.observe_eval(torch.tensor([False, True, True]), 200)
    np.testing.assert_allclose(s._weight[:3].numpy(), [1 / 3, 1, 1])
    g = ProtoMotionsSampler(6, ProtoMotionsConfig(failure_decay=0.5, min_weight=0.01))
    g.set_clips(CLIPS, LAST, 3)
    g.observe_eval(torch.tensor([True, False, False]), 1)
    np.testing.assert_allclose(g._weight[:3].numpy(), [2.0, 0.999, 0.999])


# ---------------------------------------------------------------------------------------------- properties
def _random_peer(kind: str, rng: np.random.Generator):
    s = make_sampler(load_variant(kind), 6)
    s.set_clips(CLIPS, LAST, 3)
    return s


@pytest.mark.parametrize("kind", PEERS)
def test_probabilities_stay_a_distribution_under_random_updates(kind):
    rng = np.random.default_rng(0)
    s = _random_peer(kind, rng)
    for _ in range(300):
        episodes = torch.as_tensor(rng.integers(0, 5, 6), dtype=torch.float64)
        s.update_counts(episodes, torch.minimum(episodes, torch.as_tensor(rng.integers(0, 3, 6), dtype=torch.float64)))
        steps = torch.as_tensor(rng.integers(0, 4, 6), dtype=torch.float64)
        s.update_errors(torch.as_tensor(rng.random((len(ERROR_COMPONENTS), 6))) * steps, steps)
        s.observe_eval(torch.as_tensor(rng.random(3) < 0.5), int(rng.integers(1, 300)))
        p = s.probabilities()
        assert torch.isfinite(p).all() and (p >= 0).all() and math.isclose(float(p.sum()), 1.0, rel_tol=1e-12)
        if kind == "egm":  # the uniform ratio is a floor
            assert float(p.min()) >= float(s.schedule()[1]) / 6 - 1e-15
        if kind == "protomotions":
            assert float(s._weight[:3].min()) >= 1 / 3 - 1e-15
        draws = s.sample(64)
        assert bool((p[draws] > 0).all())  # never a bin of probability 0


@pytest.mark.parametrize("kind", PEERS)
def test_state_dict_round_trip(kind):
    rng = np.random.default_rng(1)
    a, b = _random_peer(kind, rng), _random_peer(kind, rng)
    a.update_counts(torch.tensor([5.0, 1, 0, 2, 0, 9]), torch.tensor([1.0, 0, 0, 1, 0, 0]))
    a.update_errors(torch.rand(len(ERROR_COMPONENTS), 6, dtype=torch.float64), torch.ones(6, dtype=torch.float64))
    a.observe_eval(torch.tensor([True, False, False]), 50)
    b.load_state_dict(a.state_dict())
    np.testing.assert_array_equal(_probs(a), _probs(b))


# ---------------------------------------------------------------------------------------------- accounting
def _state(ref_pos, robot_pos, n_bodies=2):
    ref = torch.as_tensor(ref_pos, dtype=torch.float32)
    quat = torch.tensor([1.0, 0, 0, 0]).expand(len(ref), n_bodies, 4)
    zeros = torch.zeros(len(ref), n_bodies, 3)
    return SimpleNamespace(ref_body_pos_relative=ref, robot_body_pos=torch.as_tensor(robot_pos, dtype=torch.float32),
                           ref_body_quat_relative=quat, robot_body_quat=quat, ref_body_lin_vel=zeros,
                           robot_body_lin_vel=zeros)


class _Recorder:
    signals = (TRACKING_ERRORS,)

    def __init__(self):
        self.calls = []

    def update_errors(self, sums, steps):
        self.calls.append((sums.clone(), steps.clone()))

    def update_counts(self, episodes, failures):
        pass


def test_feedback_sums_errors_per_bin_of_the_current_frame_and_charges_broken_worlds_a_lost_track():
    """A broken world (env 2, NaN state) is charged BROKEN_ERRORS, the hardest failure an
    error-driven sampler can see (issue 36: it was skipped, so a bin that blew up looked easy)."""
    from bmimic.envs.state import tracking_errors
    from bmimic.sampling.feedback import BROKEN_ERRORS

    layout = SimpleNamespace(num_bins=3, bins_of=lambda frames: frames // 10)
    rec = _Recorder()
    acc = SamplerFeedback(rec, layout, num_envs=3, max_episode_length=100)
    # env 0 at frame 5 (bin 0): bodies 0.3 m and 0.1 m off; env 1 at frame 25 (bin 2): 0.2 m, 0; env 2 broken
    ref = [[[0, 0, 0], [0, 0, 0]]] * 3
    robot = [[[0.3, 0, 0], [0, 0.1, 0]], [[0, 0, 0.2], [0, 0, 0]], [[float("nan"), 0, 0], [0, 0, 0]]]
    state = _state(ref, robot)
    no = torch.zeros(3, dtype=torch.bool)
    acc.measure(torch.tensor([5, 25, 15]), torch.tensor([False, False, True]), no, torch.zeros(3),
                lambda: tracking_errors(state))
    acc.end_rollout()
    sums, steps = rec.calls[0]
    assert np.isfinite(sums.numpy()).all()
    np.testing.assert_allclose(steps.numpy(), [1, 1, 1])
    np.testing.assert_allclose(sums[0].numpy(), [0.2, BROKEN_ERRORS[0], 0.1], rtol=1e-6)  # mean body position error
    np.testing.assert_allclose(sums[3].numpy(), [0.3, BROKEN_ERRORS[3], 0.2], rtol=1e-6)  # largest body position error
    np.testing.assert_allclose(sums[1].numpy(), [0, BROKEN_ERRORS[1], 0], atol=1e-6)
    acc.end_rollout()  # cleared after each rollout
    assert float(rec.calls[1][1].sum()) == 0


def test_feedback_measures_nothing_for_samplers_without_errors():
    layout = SimpleNamespace(num_bins=2, bins_of=lambda f: f)
    acc = SamplerFeedback(make_sampler(load_variant("adaptive"), 2), layout, num_envs=1, max_episode_length=10)
    assert not acc.wants(TRACKING_ERRORS)

    def never():
        raise AssertionError("the errors were computed for a sampler that does not declare them")

    acc.measure(torch.tensor([0]), torch.tensor([False]), torch.tensor([False]), torch.zeros(1), never)


def test_clips_failed_from_the_clip_rollouts():
    rollouts = pd.DataFrame({"clip": [2, 0, 1], "failed": [True, True, False]})  # one rollout per clip
    assert clips_failed(rollouts, 3).tolist() == [True, False, True]


# ---------------------------------------------------------------------------------------------- config
def test_clip_samplers_refuse_clip_balance_clips():
    for kind in ("gmt", "phc", "protomotions"):
        cfg = load_variant(kind)
        cfg.clip_balance = "clips"
        with pytest.raises(SamplerConfigError, match="clip_balance"):
            validate_sampler_config(cfg)


@pytest.mark.parametrize("key,value", [("ema", 0.0), ("power_end", 0.0), ("uniform_start", 1.5),
                                       ("schedule_iterations", 0), ("weight_body_pos", -1.0)])
def test_egm_range_checks(key, value):
    cfg = load_variant("egm")
    setattr(cfg, key, value)
    with pytest.raises(SamplerConfigError, match=key):
        validate_sampler_config(cfg)


def test_egm_schedule_spans_the_run_unless_set():
    from bmimic.config import resolve_runtime
    from tests.conftest import compose

    cfg = compose(["sampler=egm", "max_iterations=600"])
    resolve_runtime(cfg, "cpu")
    assert cfg.sampler.schedule_iterations == 600
    cfg = compose(["sampler=egm", "max_iterations=600", "sampler.schedule_iterations=50"])
    resolve_runtime(cfg, "cpu")
    assert cfg.sampler.schedule_iterations == 50
    assert make_sampler(load_variant("egm"), 3).schedule_iterations == UNSET_SCHEDULE_ITERATIONS


def test_eval_driven_sampler_needs_the_periodic_evaluation():
    from bmimic.config import ConfigError, resolve_runtime
    from bmimic.config.checks import validate
    from tests.conftest import compose

    cfg = compose(["sampler=phc", "eval.every_iters=0"])
    resolve_runtime(cfg, "cpu")
    with pytest.raises(ConfigError, match="eval.every_iters"):
        validate(cfg, motion_duration_s=30.0)


def test_an_evaluation_interval_beyond_the_budget_is_flagged_for_eval_driven_samplers():
    from bmimic.config import resolve_runtime
    from bmimic.config.checks import advisories
    from tests.conftest import compose

    def notes(*overrides):
        cfg = compose(list(overrides))
        resolve_runtime(cfg, "cpu")
        return advisories(cfg)

    (note,) = notes("sampler=phc", "eval.every_iters=100", "max_iterations=50")
    assert "sampler=phc" in note and "eval.every_iters=100" in note and "max_iterations=50" in note
    assert len(notes("sampler=protomotions", "eval.every_iters=4", "max_iterations=4")) == 1  # only at the end
    assert notes("sampler=phc", "eval.every_iters=2", "max_iterations=4") == []
    assert notes("sampler=uniform", "eval.every_iters=100", "max_iterations=4") == []  # not eval-driven


# ---------------------------------------------------------------------------------------------- end to end
@pytest.mark.slow
@pytest.mark.parametrize("kind", PEERS)
def test_two_cpu_iterations_on_the_builtin_library(kind, tmp_path):
    short = ["sampler.rollout_max_s=0.5"] if kind in ("phc", "protomotions") else []  # the clip rollouts' length
    run = train_in_process(tmp_path / kind, *[o for o in TINY if not o.startswith("motion=")],
                           "motion=builtin_library", f"sampler={kind}", "eval.every_iters=1", "eval.episodes_per_bin=1",
                           *short)
    table = pd.read_parquet(run / "sampler.parquet")
    assert set(table["clip"]) == {"graded_s0", "graded_s1", "easy_s2"}
    for _, rows in table.groupby("iteration"):
        assert math.isclose(rows["probability"].sum(), 1.0, rel_tol=1e-9) and (rows["probability"] >= 0).all()
    ckpt = torch.load(next((run / "checkpoints").glob("*.pt")), weights_only=True, map_location="cpu")
    assert ckpt["sampler"]["kind"] == kind
    if short:  # one rollout per clip from its first frame at each of the 2 evaluations, 0.5 s = 25 steps
        rollouts = pd.read_parquet(run / "clip_eval.parquet")
        assert rollouts.groupby("iteration")["clip_name"].apply(list).to_dict() == {
            i: ["graded_s0", "graded_s1", "easy_s2"] for i in (1, 2)}
        assert (rollouts["steps"] <= 25).all() and (rollouts["steps"][~rollouts["failed"]] == 25).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("kind", PEERS)
def test_peer_hot_path_has_no_host_sync(kind):
    """Error tracking in the step, the per-rollout update, an evaluation's update and sampling never
    wait for the device."""
    from bmimic.envs.state import tracking_errors
    from bmimic.sampling.bins import BinLayout

    dev, n = torch.device("cuda"), 4096
    layout = BinLayout(3000, 50.0, 1.0, device=dev)
    s = make_sampler(load_variant(kind), layout.num_bins, dev)
    acc = SamplerFeedback(s, layout, n, 500, device=dev)
    g = torch.Generator(device=dev).manual_seed(0)
    ref, robot = torch.randn(n, 14, 3, device=dev), torch.randn(n, 14, 3, device=dev)
    quat = torch.nn.functional.normalize(torch.randn(n, 14, 4, device=dev), dim=-1)
    state = SimpleNamespace(ref_body_pos_relative=ref, robot_body_pos=robot, ref_body_quat_relative=quat,
                            robot_body_quat=quat.roll(1, 0), ref_body_lin_vel=ref, robot_body_lin_vel=robot)
    frames = torch.randint(0, 3000, (n,), device=dev, generator=g)
    done = torch.rand(n, device=dev, generator=g) < 0.1
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        acc.start_episodes(done, s.sample(n, generator=g))
        acc.measure(frames, done, done, frames.float(), lambda: tracking_errors(state))
        acc.record(acc.count(done, done & ~done, frames, frames, done, done & ~done, frames % 500))
        acc.end_rollout()
        s.observe_eval(torch.rand(1, device=dev, generator=g) < 0.5, 100)
        layout.sample_frames(s.sample(n, generator=g), generator=g)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    p = s.probabilities()
    assert torch.isfinite(p).all() and abs(float(p.sum()) - 1.0) < 1e-9


@pytest.mark.parametrize("kind", PEERS)
def test_yaml_schema_and_constructor_defaults_agree(kind):
    """The values of conf/sampler/<kind>.yaml are its schema's defaults, and the class built without a
    config has them too (one source of truth for the numbers the headers cite)."""
    import dataclasses
    import inspect

    from bmimic.sampling.registry import sampler_entry

    entry = sampler_entry(kind)
    assert dataclasses.asdict(load_variant(kind)) == dataclasses.asdict(entry.config())
    built = make_sampler(entry.config(), 6).hparams()
    plain = entry.cls(6).hparams()
    assert built == plain
    assert set(inspect.signature(entry.cls).parameters) >= {"num_bins", "device"}


@pytest.mark.parametrize("kind", PEERS + ("adaptive", "uniform"))
def test_starts_move_to_a_planted_hard_segment(kind):
    """A planted answer: 3 clips of 20 bins; bins 25-29 (in clip 1) fail 80% of the episodes started
    there with 6x the tracking error, every other bin 5%. After 150 simulated iterations (an evaluation
    every 10, counted as ProtoMotions' default 200) every sampler gives those 5 bins more than 1.5x
    their uniform share (5/60), each through its own signal."""
    g = torch.Generator().manual_seed(0)
    s = make_sampler(load_variant(kind), 60)
    clips = torch.arange(60) // 20
    s.set_clips(clips, clips * 20 + 19, 3)
    hard = torch.zeros(60, dtype=torch.bool)
    hard[25:30] = True
    for it in range(150):
        starts = s.sample(512, generator=g)
        failed = torch.rand(512, generator=g) < torch.where(hard[starts], 0.8, 0.05)
        episodes = torch.zeros(60, dtype=torch.float64).index_add_(0, starts, torch.ones(512, dtype=torch.float64))
        failures = torch.zeros(60, dtype=torch.float64).index_add_(0, starts, failed.double())
        s.update_counts(episodes, failures)
        steps = episodes * 10
        s.update_errors(steps * torch.where(hard, 0.3, 0.05).double().expand(len(ERROR_COMPONENTS), 60), steps)
        if it % 10 == 9:  # an evaluation: clip 1 fails, the others rarely
            s.observe_eval(torch.tensor([False, True, False]) | (torch.rand(3, generator=g) < 0.05), 200)
    share = float(s.probabilities()[hard].sum())
    if kind == "uniform":  # the control: nothing moves
        assert math.isclose(share, 5 / 60, rel_tol=1e-12)
    else:  # (ProtoMotions' floor caps clip 1 at 1 / (1 + 2/3) of the mass, a quarter of it on the hard bins: 0.15)
        assert share > 1.5 * 5 / 60, share
