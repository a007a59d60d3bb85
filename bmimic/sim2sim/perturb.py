"""The `robust` condition in native MuJoCo: training's perturbations, drawn anew for each rollout.

The MuJoCo-Warp evaluation's robust condition (`bmimic.task.build_evaluator(robust=True)`) turns the
training env's event terms and observation noise back on. Here each term that has a numpy version is
applied to one native-MuJoCo rollout with the rollout's own numpy generator, with the magnitudes and
intervals of the run's env config (`env.policy_observations.<term>.noise`, `env.events`):

- observation noise: uniform in +-`noise` on every entry of the policy input term of that name, each
  control step (`env.observation_noise`);
- `push_root_velocity` (interval: every U(interval_range_s) seconds, the first after one such draw;
  reset: once at the start): a uniform root velocity change, linear in the world frame, angular drawn
  in the world frame and written in the free joint's body frame, after the step's terminations, as the
  env does;
- `randomize_foot_friction`, `offset_body_com`, `offset_default_joint_pos` (startup): one draw per
  rollout of the soles' sliding friction, the body's centre-of-mass offset, and the default pose's
  calibration offset (the action offset and the joint observation's origin).

An event term with another function (a user's `module:function`) has no native version: it is left
out and named in `skipped`, never silently. The draws are uniform like training's (bmimic.envs.noise),
but from numpy's generator, so the same seed does not give the same numbers as on MuJoCo-Warp.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, cast

import numpy as np

from bmimic.motion.math import quat_rotate_inverse

if TYPE_CHECKING:
    from bmimic.sim2sim.rollout import Rollout
    from bmimic.sim2sim.spec import PolicySpec

STARTUP_EVENTS = ("randomize_foot_friction", "offset_body_com", "offset_default_joint_pos")
"""Startup event functions with a native version (one draw per rollout)."""
PUSH_EVENT = "push_root_velocity"
"""The interval / reset event function with a native version."""


@dataclass
class Push:
    """One push term: when (`interval_range_s`, or None for a push at the rollout's start) and how hard."""

    name: str
    """The term's name in env.events."""
    lin_vel_mps: np.ndarray
    """Half-widths of the linear velocity change along world x, y, z."""
    ang_vel_radps: np.ndarray
    """Half-widths of the angular velocity change about world x, y, z."""
    interval_range_s: tuple[float, float] | None
    """[low, high] seconds between two pushes (mode interval); None: once, at the start (mode reset)."""


@dataclass
class Perturbations:
    """What the robust condition applies in native MuJoCo (module docstring); all zeros: nothing."""

    obs_noise: np.ndarray
    """[obs_dim] half-width of the uniform noise on each policy input entry (0: none)."""
    pushes: list[Push] = field(default_factory=list)
    """Push terms, in config order."""
    foot_friction_range: tuple[float, float] | None = None
    """[low, high] of the soles' sliding friction, one draw per rollout (None: the model's)."""
    com_offsets: list[tuple[str, np.ndarray]] = field(default_factory=list)
    """(body, half-widths along x, y, z in m) of centre-of-mass offsets."""
    default_joint_offset_rad: float = 0.0
    """Half-width of the per-joint calibration offset of the default pose."""
    applied: list[str] = field(default_factory=list)
    """Names of the env.events terms (and `observation_noise`) applied."""
    skipped: list[str] = field(default_factory=list)
    """`name (func)` of the enabled event terms without a native version (not applied)."""
    source: str = ""
    """Where the magnitudes were read (the run's config, or bmimic's default env config)."""


def perturbations_from_env(env: dict, spec: PolicySpec, source: str) -> Perturbations:
    """The robust condition of `env` (a resolved `env` config section as plain values) for the policy
    input of `spec`: observation noise by term name, and the events with a native version."""
    noise = np.zeros(spec.obs_dim)
    applied, skipped = [], []
    if env.get("observation_noise", True):
        terms = env.get("policy_observations") or {}
        i = 0
        for term in spec.obs_terms:
            half_width = float((terms.get(term.name) or {}).get("noise") or 0.0)
            noise[i:i + term.dim] = half_width
            i += term.dim
        if noise.any():
            applied.append("observation_noise")
    out = Perturbations(obs_noise=noise, source=source)
    events = (env.get("events") or {}) if env.get("events_enabled", True) else {}
    for name, term in events.items():
        if not term.get("enabled", True):
            continue
        func, mode, params = str(term.get("func")), term.get("mode", "startup"), term.get("params") or {}
        if func == PUSH_EVENT and mode in ("interval", "reset"):
            interval = cast(tuple[float, float], tuple(float(x) for x in term["interval_range_s"])) \
                if mode == "interval" else None
            out.pushes.append(Push(name, np.asarray(params["lin_vel_mps"], dtype=float),
                                   np.asarray(params["ang_vel_radps"], dtype=float), interval))
        elif func == "randomize_foot_friction" and mode == "startup":
            lo, hi = params["friction_range"]
            out.foot_friction_range = (float(lo), float(hi))
        elif func == "offset_body_com" and mode == "startup":
            out.com_offsets.append((str(params["body"]), np.asarray(params["offset_m"], dtype=float)))
        elif func == "offset_default_joint_pos" and mode == "startup":
            out.default_joint_offset_rad += float(params["offset_rad"])
        else:
            skipped.append(f"{name} ({func}, {mode})")
            continue
        applied.append(name)
    out.applied, out.skipped = applied, skipped
    return out


def foot_geoms(mjm, spec: PolicySpec) -> np.ndarray:
    """The geoms randomize_foot_friction draws for: those with contact priority (the soles, which govern
    their contacts), else the end effectors' colliding geoms (bmimic.envs.mdp.events' rule)."""
    feet = np.flatnonzero(mjm.geom_priority > 0)
    if len(feet):
        return feet
    ee = {mjm.body(n).id for n in spec.end_effector_bodies}
    return np.array([g for g in range(mjm.ngeom) if int(mjm.geom_bodyid[g]) in ee and mjm.geom_contype[g]],
                    dtype=np.int64)


class Draw:
    """One rollout's perturbations: `start` before the rollout's reset (model fields, default pose,
    noise), `after_reset` (reset-mode pushes, first push times), `after_step` (interval pushes, after
    the step's terminations), `finish` (the model's fields back as they were)."""

    def __init__(self, perturbations: Perturbations, rng: np.random.Generator) -> None:
        self.p, self.rng = perturbations, rng
        self.time_left_s = np.zeros(len(perturbations.pushes))
        self.pushes = 0
        """Pushes applied so far."""
        self._saved: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def _uniform(self, half_width) -> np.ndarray:
        hw = np.asarray(half_width, dtype=float)
        return (2.0 * self.rng.random(hw.shape) - 1.0) * hw

    def _set(self, field_: np.ndarray, index, value) -> None:
        self._saved.append((field_, index, field_[index].copy()))
        field_[index] = value

    def start(self, rollout: Rollout) -> None:
        p, m = self.p, rollout.m
        if p.foot_friction_range is not None:
            lo, hi = p.foot_friction_range
            feet = foot_geoms(m, rollout.spec)
            self._set(m.geom_friction, (feet, 0), lo + (hi - lo) * self.rng.random())
        for body, half_widths in p.com_offsets:
            b = m.body(body).id
            self._set(m.body_ipos, b, m.body_ipos[b] + self._uniform(half_widths))
        rollout.default_joint_pos = rollout.spec.default_joint_pos + self._uniform(
            np.full(len(rollout.spec.joint_names), p.default_joint_offset_rad))
        rollout.obs_noise, rollout.rng = (p.obs_noise, self.rng) if p.obs_noise.any() else (None, None)

    def _draw_interval(self, push: Push) -> float:
        assert push.interval_range_s is not None, "only an interval push draws its next time"
        lo, hi = push.interval_range_s
        return lo + (hi - lo) * self.rng.random()

    def after_reset(self, rollout: Rollout) -> None:
        for k, push in enumerate(self.p.pushes):
            if push.interval_range_s is None:
                self.push(rollout, push)
            else:
                self.time_left_s[k] = self._draw_interval(push)

    def after_step(self, rollout: Rollout) -> None:
        for k, push in enumerate(self.p.pushes):
            if push.interval_range_s is None:
                continue
            self.time_left_s[k] -= rollout.spec.control_dt_s
            if self.time_left_s[k] <= 0:
                self.push(rollout, push)
                self.time_left_s[k] = self._draw_interval(push)

    def push(self, rollout: Rollout, push: Push) -> None:
        """Add a uniform root velocity change (bmimic.envs.mdp.events.push_root_velocity)."""
        d, fq, fv = rollout.d, rollout.free_q, rollout.free_v
        dv = self._uniform(push.lin_vel_mps)
        dw_world = self._uniform(push.ang_vel_radps)
        d.qvel[fv:fv + 3] += dv
        d.qvel[fv + 3:fv + 6] += quat_rotate_inverse(d.qpos[fq + 3:fq + 7].copy(), dw_world)
        rollout.touch()
        self.pushes += 1

    def finish(self, rollout: Rollout) -> None:
        for field_, index, value in reversed(self._saved):
            field_[index] = value
        self._saved.clear()
        rollout.default_joint_pos = rollout.spec.default_joint_pos
        rollout.obs_noise = rollout.rng = None


__all__ = ["PUSH_EVENT", "STARTUP_EVENTS", "Draw", "Perturbations", "Push", "foot_geoms", "perturbations_from_env"]
