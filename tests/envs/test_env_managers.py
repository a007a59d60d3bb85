"""The environment's term managers and event terms, directly: known answers on planted terms."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from bmimic.envs.config import (
    EnvConfigError,
    EventTermConfig,
    ObsTermConfig,
    RewardTermConfig,
    TerminationTermConfig,
    check_env,
)
from bmimic.envs.managers import EventManager, ObservationManager, RewardManager, TerminationManager
from bmimic.envs.noise import UniformNoise

CALLS: dict[str, int] = {}
"""Calls of the planted terms below, by name (reset by each test)."""


def _term(name: str) -> str:
    """A config's name for a planted function of this module (wherever the test file lives)."""
    return f"{__name__}:{name}"


def planted_value(env, value: float, name: str = "value") -> torch.Tensor:
    CALLS[name] = CALLS.get(name, 0) + 1
    return torch.full((env.num_envs,), float(value))


def planted_column(env, value: float) -> torch.Tensor:
    return torch.full((env.num_envs, 1), float(value))


def planted_flags(env, envs_hit: list) -> torch.Tensor:
    return torch.tensor([i in envs_hit for i in range(env.num_envs)])


def planted_event(env, envs: torch.Tensor, name: str = "event") -> None:
    CALLS[name] = CALLS.get(name, 0) + 1
    env.fired.append(envs.clone())


@pytest.fixture(autouse=True)
def _reset_calls():
    CALLS.clear()


def _env(n: int = 3):
    return SimpleNamespace(num_envs=n, device=torch.device("cpu"), fired=[])


def test_weight_zero_reward_term_is_not_computed_but_logged_as_zero():
    cfgs = {
        "a": RewardTermConfig(func=_term("planted_value"), weight=2.0, params={"value": 1.5, "name": "a"}),
        "off": RewardTermConfig(func=_term("planted_value"), weight=0.0, params={"value": 7.0, "name": "off"}),
        "b": RewardTermConfig(func=_term("planted_value"), weight=-1.0, params={"value": 0.5, "name": "b"}),
    }
    env = _env()
    rm = RewardManager(cfgs, step_dt=0.02, num_envs=3, device="cpu")
    rewards = rm.compute(env)
    assert CALLS == {"a": 1, "b": 1}  # the weight-0 term never ran
    assert torch.allclose(rewards, torch.tensor([[2.0 * 1.5 * 0.02, 0.0, -1.0 * 0.5 * 0.02]] * 3))
    rm.accumulate(rewards)
    log = rm.pop_log(episodes=0.0)
    assert list(log) == ["reward/a", "reward/off", "reward/b", "mean_episode_reward"]
    assert all(math.isnan(v) for v in log.values())  # no finished episode yet


def test_reward_episode_sums_per_term_and_episode_means():
    cfgs = {"a": RewardTermConfig(func=_term("planted_value"), weight=1.0, params={"value": 1.0}),
            "b": RewardTermConfig(func=_term("planted_value"), weight=0.5, params={"value": 2.0})}
    env = _env()
    rm = RewardManager(cfgs, step_dt=0.5, num_envs=3, device="cpu")  # a: 0.5 a step, b: 0.5 a step
    for _ in range(4):
        rm.accumulate(rm.compute(env))
    assert torch.allclose(rm.episode_sums, torch.full((3, 2), 2.0))
    rm.end_episodes(torch.tensor([True, False, True]))  # envs 0 and 2 finish after 4 steps
    assert torch.allclose(rm.episode_sums, torch.tensor([[0.0, 0.0], [2.0, 2.0], [0.0, 0.0]]))
    rm.accumulate(rm.compute(env))
    rm.end_episodes(torch.tensor([False, True, False]))  # env 1 finishes after 5 steps
    log = rm.pop_log(episodes=3.0)
    assert log["reward/a"] == pytest.approx((2.0 + 2.0 + 2.5) / 3)
    assert log["reward/b"] == pytest.approx((2.0 + 2.0 + 2.5) / 3)
    assert log["mean_episode_reward"] == pytest.approx(2 * 6.5 / 3)
    assert rm.pop_log(episodes=1.0)["reward/a"] == 0.0  # popped sums are cleared


def test_terminations_split_time_outs_and_count_each_term():
    cfgs = {"time_out": TerminationTermConfig(func=_term("planted_flags"), time_out=True, params={"envs_hit": [0]}),
            "fell": TerminationTermConfig(func=_term("planted_flags"), params={"envs_hit": [1, 2]}),
            "off": TerminationTermConfig(func=_term("planted_flags"), enabled=False, params={"envs_hit": [0, 1, 2]})}
    tm = TerminationManager(cfgs, "cpu")
    env = _env()
    flags = tm.compute(env)
    assert flags.shape == (3, 2)  # the disabled term is neither computed nor a column
    assert tm.time_outs(flags).tolist() == [True, False, False]
    assert tm.terminations(flags).tolist() == [False, True, True]
    tm.compute(env)
    log = tm.pop_log(steps=2.0, num_envs=3)
    assert log == {"termination/time_out": pytest.approx(2 / 6), "termination/fell": pytest.approx(4 / 6)}


def test_observation_noise_only_in_the_noisy_group():
    terms = {"x": ObsTermConfig(func=_term("planted_column"), noise=0.5, params={"value": 1.0})}
    om = ObservationManager({"policy": (terms, True), "critic": (terms, False), "empty": ({}, False)},
                            UniformNoise("cpu"), num_envs=3, device="cpu")
    obs = om.compute(_env())
    assert set(obs.keys()) == {"policy", "critic"}  # an empty group other than the first is left out
    assert torch.equal(obs["critic"], torch.ones(3, 1))
    noise = obs["policy"] - 1.0
    assert (noise.abs() <= 0.5).all() and (noise != 0).any()


def test_interval_event_fires_at_its_period():
    """interval_range_s = [0.25, 0.25] and dt = 1/16 s (exact in float32): every 4th step, all worlds."""
    cfgs = {"kick": EventTermConfig(func=_term("planted_event"), mode="interval", interval_range_s=[0.25, 0.25])}
    em = EventManager(cfgs, num_envs=3, device="cpu")
    env = _env()
    em.startup(env)
    due = []
    for _ in range(12):
        env.fired.clear()
        em.interval(env, 1.0 / 16)
        due.append(bool(env.fired[0].all()) if env.fired[0].any() else False)
    assert CALLS["event"] == 12  # it runs every step, masked to the due worlds
    assert [i + 1 for i, d in enumerate(due) if d] == [4, 8, 12]


def test_interval_timers_are_per_world():
    cfgs = {"kick": EventTermConfig(func=_term("planted_event"), mode="interval", interval_range_s=[0.1, 0.5])}
    em = EventManager(cfgs, num_envs=64, device="cpu")
    env = _env(64)
    torch.manual_seed(0)
    em.startup(env)
    (time_left,) = em.time_left_s
    assert ((time_left >= 0.1) & (time_left <= 0.5)).all() and time_left.std() > 0
    first = time_left.clone()
    em.interval(env, 0.3)
    assert env.fired[-1].tolist() == (first <= 0.3).tolist()


def test_startup_and_reset_events_run_in_their_worlds():
    cfgs = {"once": EventTermConfig(func=_term("planted_event"), mode="startup", params={"name": "once"}),
            "again": EventTermConfig(func=_term("planted_event"), mode="reset", params={"name": "again"}),
            "never": EventTermConfig(func=_term("planted_event"), mode="reset", enabled=False, params={"name": "no"})}
    em = EventManager(cfgs, num_envs=3, device="cpu")
    env = _env()
    em.startup(env)
    assert CALLS == {"once": 1} and env.fired[0].all()
    em.reset(env, torch.tensor([False, True, False]))
    assert CALLS == {"once": 1, "again": 1} and env.fired[1].tolist() == [False, True, False]
    assert not em.has_interval


def test_event_model_fields_come_from_the_terms():
    from bmimic.envs.config import EnvConfig

    cfgs = {"f": EventTermConfig(func="randomize_foot_friction", params={"friction_range": [0.5, 1.0]}),
            "c": EventTermConfig(func="offset_body_com", params={"body": "torso_link", "offset_m": [0.0, 0.0, 0.0]}),
            "p": EventTermConfig(func="push_root_velocity", mode="interval", interval_range_s=[1.0, 2.0],
                                 params={"lin_vel_mps": [0, 0, 0], "ang_vel_radps": [0, 0, 0]})}
    assert EventManager(cfgs, 2, "cpu").model_fields == ("geom_friction", "body_ipos")
    check_env(EnvConfig(policy_observations={"x": ObsTermConfig(func="last_action")}, events=cfgs))


@pytest.mark.parametrize("change, key", [
    ({"mode": "interval", "interval_range_s": [1.0, 2.0]}, "env.events.f.mode"),  # a startup-only term
    ({"params": {"friction_range": [2.0, 1.0]}}, "env.events.f.params.friction_range"),
    ({"params": {"friction_range": [0.5, 1.0], "extra": 1}}, "env.events.f.params"),
    ({"func": "no_such_event"}, "env.events.f.func"),
])
def test_event_config_errors_name_the_key(change, key):
    from bmimic.envs.config import EnvConfig

    term = EventTermConfig(func="randomize_foot_friction", params={"friction_range": [0.5, 1.0]})
    for k, v in change.items():
        setattr(term, k, v)
    cfg = EnvConfig(policy_observations={"x": ObsTermConfig(func="last_action")}, events={"f": term})
    with pytest.raises(EnvConfigError, match=key.replace(".", r"\.")):
        check_env(cfg)


def test_startup_event_runs_once_before_the_step_is_captured():
    """A real training environment: the startup term has run (once, in every world) when the
    constructor returns, i.e. before any graph capture; steps never run it again."""
    from omegaconf import open_dict

    from bmimic.config import resolve_runtime
    from bmimic.runtime import seed_everything
    from bmimic.task import build_training
    from tests.conftest import compose

    seed_everything(0)
    cfg = compose(["motion=easy_only", "num_envs=2", "device=cpu"])
    with open_dict(cfg.env.events):
        cfg.env.events.planted = EventTermConfig(func=_term("planted_startup"), mode="startup")
    resolve_runtime(cfg, "cpu")
    env = build_training(cfg, "cpu").env
    assert STARTUP == [(2, True, False)]  # once, all worlds, no step taken yet
    for _ in range(3):
        env.step(torch.zeros(2, env.num_actions))
    assert len(STARTUP) == 1


STARTUP: list = []


def planted_startup(env, envs: torch.Tensor) -> None:
    STARTUP.append((int(envs.sum()), bool(envs.all()), hasattr(env, "_obs")))
