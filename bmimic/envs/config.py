"""Schema of the `env` config group: the tracking MDP as named term functions with parameters.

Every observation, reward, termination and event term names a plain function in `bmimic.envs.mdp`
(or `package.module:function`) with its parameters, so an ablation of the MDP is a config override:
`env.rewards.action_rate.weight=0`, `env.terminations.ee_body_pos.params.threshold_m=0.3`,
`env.events.push.enabled=false`. `check_env` checks the meaning of the whole group once.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Dict, List, Optional

from bmimic import BmimicError

if TYPE_CHECKING:
    from bmimic.sim.config import SimConfig

EVENT_MODES = ("startup", "interval", "reset")


@dataclass
class ObsTermConfig:
    func: str = "???"
    """Observation function name in bmimic.envs.mdp.observations (or `module:function`)."""
    noise: float = 0.0
    """Half-width of additive uniform noise, applied when the group is corrupted (policy, training)."""
    params: Dict[str, Any] = field(default_factory=dict)
    """Keyword arguments passed to the function."""


@dataclass
class RewardTermConfig:
    func: str = "???"
    """Reward function name in bmimic.envs.mdp.rewards (or `module:function`)."""
    weight: float = 1.0
    """Weight; the step reward is sum(weight * term) * step_dt, as in BeyondMimic. 0 switches the term
    off: it is not computed and its logged episode sum stays 0."""
    params: Dict[str, Any] = field(default_factory=dict)
    """Keyword arguments passed to the function."""


@dataclass
class TerminationTermConfig:
    func: str = "???"
    """Termination function name in bmimic.envs.mdp.terminations (or `module:function`)."""
    time_out: bool = False
    """A time-out is a truncation (bootstrapped, never a failure) rather than a termination."""
    enabled: bool = True
    """Disabled terms are neither computed nor applied."""
    params: Dict[str, Any] = field(default_factory=dict)
    """Keyword arguments passed to the function."""


@dataclass
class ResetConfig:
    """Reference-state initialisation: the robot starts at the reference frame plus uniform noise."""

    root_pos_range_m: List[float] = field(default_factory=lambda: [0.05, 0.05, 0.01])
    """Half-widths of the root position offset along world x, y, z."""
    root_rot_range_rad: List[float] = field(default_factory=lambda: [0.1, 0.1, 0.2])
    """Half-widths of the root roll, pitch, yaw offset (left-multiplied)."""
    root_lin_vel_range_mps: List[float] = field(default_factory=lambda: [0.5, 0.5, 0.2])
    """Half-widths of the root linear velocity offset."""
    root_ang_vel_range_radps: List[float] = field(default_factory=lambda: [0.52, 0.52, 0.78])
    """Half-widths of the root angular velocity offset."""
    joint_pos_range_rad: float = 0.1
    """Half-width of the joint position offset (then clipped to the soft joint limits)."""


@dataclass
class EventTermConfig:
    func: str = "???"
    """Event function name in bmimic.envs.mdp.events (or `module:function`): f(env, envs, **params),
    `envs` the Bool[num_envs] mask of the worlds it applies to now."""
    mode: str = "startup"
    """When it runs: `startup` (once per world when the environment is built, before the step is
    captured), `interval` (in each world every interval_range_s, drawn anew after each firing) or
    `reset` (in the worlds that start a new episode)."""
    interval_range_s: Optional[List[float]] = None
    """mode=interval: [low, high] seconds between two firings in a world, drawn uniformly per world."""
    enabled: bool = True
    """Disabled terms never run."""
    params: Dict[str, Any] = field(default_factory=dict)
    """Keyword arguments passed to the function."""


@dataclass
class EnvConfig:
    """The BeyondMimic tracking MDP (notes section 3)."""

    episode_length_s: float = 10.0
    """Episode length; reaching it is a time-out (truncation)."""
    max_abs_step_reward: float = 1.0e6
    """A world whose step reward is larger than this in magnitude (or not finite) is reset and counted,
    its reward zeroed: one broken world must never reach the value loss."""
    observation_noise: bool = True
    """Corrupt the policy group with each term's uniform noise during training (and robust evaluation)."""
    policy_observations: Dict[str, ObsTermConfig] = field(default_factory=dict)
    """Terms of the `policy` group, concatenated in this order (BeyondMimic: 160 dims)."""
    critic_observations: Dict[str, ObsTermConfig] = field(default_factory=dict)
    """Terms of the privileged `critic` group, never corrupted (BeyondMimic: 286 dims)."""
    rewards: Dict[str, RewardTermConfig] = field(default_factory=dict)
    """Reward terms; each is logged separately under reward/<name>."""
    terminations: Dict[str, TerminationTermConfig] = field(default_factory=dict)
    """Termination terms; each is logged separately under termination/<name>."""
    reset: ResetConfig = field(default_factory=ResetConfig)
    """Reference-state initialisation noise."""
    events_enabled: bool = True
    """Run the event terms in training (and robust evaluation); false: no domain randomisation and
    no pushes. The plain evaluation, play and export never run them."""
    events: Dict[str, EventTermConfig] = field(default_factory=dict)
    """Domain randomisation and pushes as event terms (BeyondMimic ranges, notes section 3.6), run
    in this order within each mode."""


def episode_length_steps(env_cfg: EnvConfig, sim_cfg: SimConfig) -> int:
    """Control steps of a full episode (`env.episode_length_s` rounded up; sim_cfg: a SimConfig)."""
    return int(math.ceil(env_cfg.episode_length_s / (sim_cfg.timestep_s * sim_cfg.decimation)))


class EnvConfigError(BmimicError, ValueError):
    """A value of the `env` group that makes no sense; the message is one line naming the key."""


def _fail(key: str, problem: str) -> None:
    raise EnvConfigError(f"{key}: {problem}")


def _check_half_widths(key: str, value: Any, length: int) -> None:
    value = list(value) if length > 1 else [value]
    if len(value) != length or any(v < 0 for v in value):
        what = f"{length} half-widths" if length > 1 else "a half-width"
        _fail(key, f"must be {what} >= 0, got {value if length > 1 else value[0]}")


TERM_GROUPS = {
    "policy_observations": "observations",
    "critic_observations": "observations",
    "rewards": "rewards",
    "terminations": "terminations",
    "events": "events",
}
"""Each term table of the env group and the kind of function its entries name."""


def check_env(cfg: EnvConfig) -> None:
    """Check the meaning of an env group (EnvConfig or the composed node): reset noise ranges, that
    every term names a function, the event modes, intervals and parameters. Raises EnvConfigError."""
    from bmimic.envs.mdp import resolve_term

    r = cfg.reset
    for key in ("root_pos_range_m", "root_rot_range_rad", "root_lin_vel_range_mps", "root_ang_vel_range_radps"):
        _check_half_widths(f"env.reset.{key}", getattr(r, key), 3)
    _check_half_widths("env.reset.joint_pos_range_rad", r.joint_pos_range_rad, 1)
    for group, kind in TERM_GROUPS.items():
        for name, term in (getattr(cfg, group) or {}).items():
            try:
                fn = resolve_term(kind, term.func)
            except LookupError as e:
                _fail(f"env.{group}.{name}.func", str(e))
            _check_signature(f"env.{group}.{name}", term, fn, kind)
            _check_scales(f"env.{group}.{name}.params", term)
            if kind == "events":
                _check_event(f"env.events.{name}", term, fn)
    if not cfg.policy_observations:
        _fail("env.policy_observations", "is empty; the policy needs at least one observation term")


POSITIVE_PARAMS = re.compile(r"^(std|threshold)(_[a-z]+)?$")
"""Term params that are a scale or a threshold (`std` of an exp(-err/std^2) reward, `threshold_m` of a
termination): > 0. A std of 0 made its reward exp(-err/0), 0 or NaN; a threshold of -1 ended every
episode at its first step (issue 77's second round)."""


def _check_scales(key: str, term: Any) -> None:
    for param, value in dict(getattr(term, "params", None) or {}).items():
        if POSITIVE_PARAMS.match(str(param)) and isinstance(value, (int, float)) and not isinstance(value, bool) \
                and not value > 0:
            _fail(f"{key}.{param}", f"is a scale or threshold and must be > 0, got {value}")


def _check_signature(key: str, term: Any, fn: Any, kind: str) -> None:
    """The term's function takes the environment (and, for events, the envs), then its params."""
    import inspect

    params = dict(getattr(term, "params", None) or {})
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):  # a builtin without a signature: cannot tell
        return
    try:
        signature.bind(None, *((None,) if kind == "events" else ()), **params)
    except TypeError as e:
        _fail(f"{key}.params", f"{term.func} cannot be called with the environment and params {sorted(params)}: {e}")


def _check_event(key: str, term: Any, fn: Any) -> None:
    modes = getattr(fn, "modes", EVENT_MODES)
    if term.mode not in modes:
        _fail(f"{key}.mode", f"{term.func} runs in mode {' or '.join(modes)}, got {term.mode!r}")
    interval = list(term.interval_range_s) if term.interval_range_s is not None else None
    if term.mode == "interval" and (interval is None or len(interval) != 2 or not 0 < interval[0] <= interval[1]):
        _fail(f"{key}.interval_range_s", f"must be [low, high] with 0 < low <= high for mode=interval, got {interval}")
    check = getattr(fn, "check_params", None)
    if check is not None:
        try:
            check(**dict(term.params or {}))
        except TypeError as e:
            _fail(f"{key}.params", f"do not fit {term.func} ({e})")
        except ValueError as e:  # "<param>: <problem>"
            param, _, problem = str(e).partition(": ")
            _fail(f"{key}.params.{param}", problem)


def foreign_term_modules(cfg: EnvConfig) -> list[str]:
    """Modules outside bmimic that the env terms name (`func: package.module:function`): importing
    them runs their code, so a run folder from elsewhere must be trusted before they are loaded."""
    found = set()
    for group in TERM_GROUPS:
        for term in (getattr(cfg, group) or {}).values():
            module = str(term.func).split(":", 1)[0] if ":" in str(term.func) else ""
            if module and module != "bmimic" and not module.startswith("bmimic."):
                found.add(module)
    return sorted(found)
