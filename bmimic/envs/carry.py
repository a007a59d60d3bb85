"""What a training environment carries from one PPO iteration to the next, as named tensors: the state a
checkpoint must hold so that a resumed run continues exactly where one unbroken run would.

Between iterations a `TrackingEnv` is mid-episode in every world. Its state lives in the simulator (the
physics state and the solver's warm start, the per-world model fields that startup events drew), the
reference segments, the episode buffers, the interval events' timers, the reward sums of the running
episodes, the sampler feedback's per-world and per-bin accumulators, and the observation the policy acts
on next (drawn with noise, so it is kept, not recomputed). `env_state` reads them all into CPU tensors;
`load_env_state` writes them back in place (captured CUDA graphs hold these buffers' addresses) after
checking every name and shape. Per-iteration logs (`IterationStats`, the managers' logged sums) are popped
at each iteration's end and are not state.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, cast

import torch
import warp as wp

from bmimic import BmimicError

if TYPE_CHECKING:
    from bmimic.envs.tracking_env import TrackingEnv

ENV_STATE_FORMAT = 1
"""Version of the names and meanings below; a checkpoint's env state of another version is not loaded."""
SIM_DATA_FIELDS = ("qpos", "qvel", "act", "qacc_warmstart", "time", "mocap_pos", "mocap_quat", "qfrc_applied",
                   "xfrc_applied")
"""MuJoCo-Warp data that one control step reads before it writes (the rest is recomputed from these)."""


class EnvStateError(BmimicError):
    """An env state that does not fit this environment (other sizes, names or format)."""


def _tensors(env: TrackingEnv) -> dict[str, torch.Tensor]:
    """The live tensors (views, not copies) that carry `env`'s state, by name."""
    sim, seg, fb = env.sim, env.segments, env.feedback
    out: dict[str, torch.Tensor] = {}
    for name in SIM_DATA_FIELDS:
        array = getattr(sim.data, name, None)
        if array is not None and array.size > 0:
            out[f"sim.{name}"] = wp.to_torch(array)
    for name in env.events.model_fields:  # per-world model fields the startup events drew
        out[f"model.{name}"] = wp.to_torch(getattr(sim.model, name))
    out.update({
        "segments.time_steps": seg.time_steps, "segments.segment_start": seg.segment_start,
        "segments.segment_end": seg.segment_end, "segments.reached_clip_end": seg.reached_clip_end,
        "episode_length": env.episode_length_buf, "actions": env.actions, "last_actions": env.last_actions,
        "default_joint_pos": env.default_joint_pos, "rewards.episode_sums": env.rewards.episode_sums,
    })
    for i, timer in enumerate(env.events.time_left_s):
        out[f"events.time_left_s.{i}"] = timer
    if fb is not None:
        out.update({"feedback.start_bin": fb.start_bin, "feedback.pending": fb._pending,
                    "feedback.errors": fb._errors, "feedback.episode_return": fb._episode_return,
                    "feedback.returns": fb._returns})
    for group, value in env._obs.items():
        out[f"obs.{group}"] = cast(torch.Tensor, value)
    return out


def env_state(env: TrackingEnv) -> dict[str, Any]:
    """Everything `env` carries into the next iteration, as CPU tensors (a checkpoint's `env`)."""
    return {"format": ENV_STATE_FORMAT, "num_envs": int(env.num_envs),
            "tensors": {k: v.detach().to("cpu", copy=True) for k, v in _tensors(env).items()}}


def load_env_state(env: TrackingEnv, state: dict[str, Any]) -> None:
    """Write `state` (from `env_state`) into `env` in place; EnvStateError naming the first mismatch,
    before anything is written."""
    if not isinstance(state, dict) or state.get("format") != ENV_STATE_FORMAT:
        raise EnvStateError(f"env state of format {state.get('format') if isinstance(state, dict) else '?'!r}, "
                            f"this bmimic reads format {ENV_STATE_FORMAT}")
    live, saved = _tensors(env), state.get("tensors")
    if not isinstance(saved, dict) or set(saved) != set(live):
        names = set(saved) if isinstance(saved, dict) else set()
        diff = sorted(names ^ set(live))
        raise EnvStateError(f"env state holds other tensors than this environment ({', '.join(diff[:4])})")
    for name, target in live.items():
        value = saved[name]
        if not isinstance(value, torch.Tensor) or value.shape != target.shape or value.dtype != target.dtype:
            got = f"{tuple(value.shape)} {value.dtype}" if isinstance(value, torch.Tensor) else type(value).__name__
            raise EnvStateError(f"env state {name}: {got}, this environment has {tuple(target.shape)} {target.dtype}")
    with torch.no_grad():
        for name, target in live.items():
            target.copy_(saved[name])
    # Body poses and velocities follow from the restored physics state; the observation was restored as
    # the policy saw it (its noise is not drawn again).
    env.sim.forward_kinematics()


__all__ = ["ENV_STATE_FORMAT", "EnvStateError", "env_state", "load_env_state"]
