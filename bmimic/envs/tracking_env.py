"""The BeyondMimic motion-tracking environment as an rsl-rl-lib `VecEnv` over the batched simulator.

One control step (`step`), all batched on the device, no host synchronisation, no per-env Python:
  1. actions -> PD targets (`ctrl`), `decimation` physics steps + kinematics (one CUDA graph on a GPU);
  2. the per-step state (robot bodies, reference frame, relative targets) is computed once;
  3. terminations, then rewards (sum of weight * term * dt);
  4. finished episodes are counted per bin (`bmimic.sampling.accounting`: attribution, failure rule);
  5. finished envs are reset at frames the sampler draws (reference-state initialisation),
     every env advances one reference frame, envs past the end of their clip are resampled and
     teleported without ending the episode (BeyondMimic); the counts go to the sampler (now, or
     once per iteration at `end_rollout`); pushes are applied;
  6. kinematics are recomputed after those state writes (no stale poses, cf. mjlab #1068) and the
     observations are built from a fresh state.
Subset resets are masked writes over all envs (`torch.where`), so shapes never depend on data.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import mujoco
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from bmimic import BmimicError
from bmimic.envs.config import EnvConfig
from bmimic.envs.mdp import resolve_term
from bmimic.envs.quat import (
    quat_apply,
    quat_apply_inverse,
    quat_conj,
    quat_from_euler_xyz,
    quat_mul,
    yaw_quat,
)
from bmimic.motion import Motion
from bmimic.robot import RobotInfo
from bmimic.sampling.accounting import EpisodeAccounting
from bmimic.sampling.bins import Layout
from bmimic.sim import SimConfig, Simulator

log = logging.getLogger(__name__)


@dataclass
class TrackingState:
    """Quantities every term reads, computed once per state (shapes [N, ...], B = tracked bodies)."""

    joint_pos: torch.Tensor
    joint_vel: torch.Tensor
    root_lin_vel_b: torch.Tensor
    root_ang_vel_b: torch.Tensor
    robot_body_pos: torch.Tensor
    robot_body_quat: torch.Tensor
    robot_body_lin_vel: torch.Tensor
    robot_body_ang_vel: torch.Tensor
    robot_anchor_pos: torch.Tensor
    robot_anchor_quat: torch.Tensor
    ref_joint_pos: torch.Tensor
    ref_joint_vel: torch.Tensor
    ref_body_pos: torch.Tensor
    ref_body_quat: torch.Tensor
    ref_body_lin_vel: torch.Tensor
    ref_body_ang_vel: torch.Tensor
    ref_anchor_pos: torch.Tensor
    ref_anchor_quat: torch.Tensor
    ref_body_pos_relative: torch.Tensor
    ref_body_quat_relative: torch.Tensor


def _plain(cfg):
    """A composed OmegaConf config as the schema's dataclass instance (others unchanged)."""
    return OmegaConf.to_object(cfg) if isinstance(cfg, DictConfig) else cfg


class _Terms:
    """Resolved term functions of one kind, with names, params and weights."""

    def __init__(self, kind: str, cfgs) -> None:
        self.names: list[str] = []
        self.funcs: list = []
        self.params: list[dict] = []
        self.cfgs: list = []
        for name, cfg in cfgs.items():
            if getattr(cfg, "enabled", True) is False:
                continue
            self.names.append(name)
            self.funcs.append(resolve_term(kind, cfg.func))
            self.params.append(dict(cfg.params) if cfg.params else {})
            self.cfgs.append(cfg)

    def __len__(self) -> int:
        return len(self.names)


class TrackingEnv(VecEnv):
    """BeyondMimic tracking of one motion (or a library of clips) by `num_envs` robots.

    `mode="train"`: domain randomisation, observation noise, pushes and automatic resets at frames
    drawn by `sampler`. `mode="eval"`: none of those; the caller places envs with `reset_to_frames`
    and reads terminations, and the reference stops at the end of each clip. `robust=True` (eval
    only) turns domain randomisation, observation noise and pushes back on, as configured for training.
    """

    def __init__(
        self,
        env_cfg: EnvConfig,
        sim_cfg: SimConfig,
        mjm: mujoco.MjModel,
        robot: RobotInfo,
        motion: Motion,
        layout: Layout,
        num_envs: int,
        device: str,
        sampler=None,
        sampler_cfg=None,
        mode: str = "train",
        robust: bool = False,
    ) -> None:
        if mode not in ("train", "eval"):
            raise ValueError(f"mode must be train or eval, got {mode!r}")
        if mode == "train" and sampler is None:
            raise ValueError("a training environment needs a sampler")
        # Plain dataclasses, not OmegaConf nodes: the step reads config fields every call, and plain
        # attribute access is cheaper and can be traced by torch.compile.
        self.cfg = _plain(env_cfg)
        self.mode = mode
        self.num_envs = num_envs
        self.device = torch.device(device)
        self.sampler = sampler
        self.sampler_cfg = _plain(sampler_cfg)
        dist = torch.distributed
        self.world_size = dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1
        self.layout = layout
        # Random draws use torch's default generator (seeded by bmimic.runtime.seed_everything), which
        # CUDA-graph replay advances (a private generator would have to be registered with every graph).
        self._half_widths: dict[tuple, torch.Tensor] = {}
        train = mode == "train"
        self.robust = robust and not train
        self.randomize = (train or self.robust) and env_cfg.randomization.enabled
        self.noise_enabled = (train or self.robust) and env_cfg.observation_noise
        self.rsi_noise = train

        control_fps = 1.0 / (sim_cfg.timestep_s * sim_cfg.decimation)
        if abs(motion.fps - control_fps) > 1e-6 * control_fps:
            # One reference frame per control step: any other rate plays the motion at the wrong speed.
            raise BmimicError(
                f"motion: is at {motion.fps:g} fps but sim.timestep_s * sim.decimation = "
                f"{sim_cfg.timestep_s:g} * {sim_cfg.decimation} s steps the policy at {control_fps:g} Hz; "
                "load it through bmimic.motion.config.load_motion(control_fps=...) to resample it")
        self._max_abs_reward = float(env_cfg.max_abs_step_reward)
        randomized = ("geom_friction", "body_ipos") if self.randomize else ()
        self.sim = Simulator(mjm, sim_cfg, num_envs, device, randomized_fields=randomized)
        self.step_dt = self.sim.control_dt
        self.max_episode_length = int(math.ceil(env_cfg.episode_length_s / self.step_dt))
        self.episode_length_buf = torch.zeros(num_envs, dtype=torch.long, device=self.device)
        self.num_actions = len(robot.joint_names)

        self._bind_robot(mjm, robot)
        self._bind_motion(motion)
        self._bind_terms()
        self._alloc_buffers()
        # Which bin each episode counts for and when the sampler sees the counts.
        self.accounting = EpisodeAccounting.from_config(
            self.sampler_cfg, sampler, layout, num_envs, self.max_episode_length, device=self.device,
            world_size=self.world_size) if train else None
        if self.randomize:
            self._randomize_startup()
        self.sim.capture()
        # Start every env at a sampled frame (train) or frame 0 (eval); the runner never calls reset.
        everyone = torch.ones(num_envs, dtype=torch.bool, device=self.device)
        if train:
            self._resample(everyone, everyone)
        else:
            self.reset_to_frames(torch.zeros(num_envs, dtype=torch.long, device=self.device))
        self.sim.forward_kinematics()
        self._observe()
        if train:
            self.capture()

    # ============================================================================ set-up
    def _bind_robot(self, mjm: mujoco.MjModel, robot: RobotInfo) -> None:
        dev = self.device
        nj = self.num_actions
        if mjm.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE or not np.array_equal(robot.qpos_adr, np.arange(7, 7 + nj)):
            raise BmimicError("robot model: expected a free joint followed by the actuated hinges in qpos")
        if mjm.nu != nj:
            raise BmimicError(f"robot model: {mjm.nu} actuators for {nj} joints; expected one per joint")
        self.robot = robot
        self.action_scale = torch.as_tensor(robot.action_scale, dtype=torch.float32, device=dev)
        self.nominal_joint_pos = torch.as_tensor(robot.default_joint_pos, dtype=torch.float32, device=dev)
        self.default_joint_pos = self.nominal_joint_pos.repeat(self.num_envs, 1)
        self.soft_joint_limits = torch.as_tensor(robot.soft_joint_limits, dtype=torch.float32, device=dev)
        self.tracked_body_ids = torch.as_tensor(robot.tracked_body_ids, dtype=torch.long, device=dev)
        tracked = [int(i) for i in robot.tracked_body_ids]
        if int(robot.anchor_body_id) not in tracked:
            raise BmimicError("robot.anchor_body must be one of robot.tracked_bodies")
        self.anchor_index = tracked.index(int(robot.anchor_body_id))
        missing = [int(i) for i in robot.end_effector_body_ids if int(i) not in tracked]
        if missing:
            raise BmimicError("robot.end_effector_bodies must all be in robot.tracked_bodies")
        self.end_effector_index = torch.as_tensor(
            [tracked.index(int(i)) for i in robot.end_effector_body_ids], dtype=torch.long, device=dev
        )
        self.gravity_w = torch.tensor([[0.0, 0.0, -1.0]], device=dev)
        # Root body of the robot tree: cvel is expressed about subtree_com of this body.
        self.root_body_id = int(mjm.body_rootid[tracked[0]])
        # Undesired contacts: any robot body except the end effectors.
        undesired = np.zeros(mjm.nbody, dtype=bool)
        undesired[1:] = True
        undesired[np.asarray(robot.end_effector_body_ids, dtype=int)] = False
        self._undesired_body = torch.as_tensor(undesired, device=dev)
        self._geom_body = torch.as_tensor(mjm.geom_bodyid, dtype=torch.long, device=dev)
        feet = [g for g in range(mjm.ngeom) if mjm.geom_priority[g] > 0]
        if not feet:
            ee = set(int(i) for i in robot.end_effector_body_ids)
            feet = [g for g in range(mjm.ngeom) if int(mjm.geom_bodyid[g]) in ee and mjm.geom_contype[g]]
        self._foot_geoms = torch.as_tensor(feet, dtype=torch.long, device=dev)
        self._torso_body = int(robot.anchor_body_id)

    def _bind_motion(self, motion: Motion) -> None:
        dev = self.device
        name_to_idx = {n: i for i, n in enumerate(motion.body_names)}
        body_names = list(self.robot.body_names)  # MuJoCo ids start at 1 (0 is the world)
        tracked_names = [body_names[int(i) - 1] for i in self.robot.tracked_body_ids]
        missing = [n for n in tracked_names + body_names[:1] if n not in name_to_idx]
        if missing:
            raise BmimicError(f"motion: has no bodies named {missing}; it was made for another robot model")
        idx = [name_to_idx[n] for n in tracked_names]
        root = name_to_idx[body_names[0]]

        def t(x):
            return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=dev)

        self.motion = motion
        self.motion_num_frames = motion.num_frames
        self.m_joint_pos = t(motion.joint_pos)
        self.m_joint_vel = t(motion.joint_vel)
        self.m_body_pos = t(motion.body_pos_w[:, idx])
        self.m_body_quat = t(motion.body_quat_w[:, idx])
        self.m_body_lin_vel = t(motion.body_lin_vel_w[:, idx])
        self.m_body_ang_vel = t(motion.body_ang_vel_w[:, idx])
        self.m_root_pos = t(motion.body_pos_w[:, root])
        self.m_root_quat = t(motion.body_quat_w[:, root])
        self.m_root_lin_vel = t(motion.body_lin_vel_w[:, root])
        self.m_root_ang_vel = t(motion.body_ang_vel_w[:, root])
        # Frame -> one past the last frame of its clip: the reference resamples there (library-ready).
        starts = list(np.asarray(motion.clip_starts, dtype=int)) + [motion.num_frames]
        clip_end = np.zeros(motion.num_frames, dtype=np.int64)
        for a, b in zip(starts[:-1], starts[1:]):
            clip_end[a:b] = b
        self.frame_clip_end = torch.as_tensor(clip_end, device=dev)

    def _bind_terms(self) -> None:
        self.policy_terms = _Terms("observations", self.cfg.policy_observations)
        self.critic_terms = _Terms("observations", self.cfg.critic_observations)
        self.reward_terms = _Terms("rewards", self.cfg.rewards)
        self.termination_terms = _Terms("terminations", self.cfg.terminations)
        self.reward_weights = torch.tensor(
            [c.weight for c in self.reward_terms.cfgs], dtype=torch.float32, device=self.device
        )
        self._timeout_term = torch.tensor(
            [bool(c.time_out) for c in self.termination_terms.cfgs], dtype=torch.bool, device=self.device
        )

    def _alloc_buffers(self) -> None:
        n, dev = self.num_envs, self.device
        self.actions = torch.zeros(n, self.num_actions, device=dev)
        self.last_actions = torch.zeros_like(self.actions)
        self.time_steps = torch.zeros(n, dtype=torch.long, device=dev)
        self.segment_start = torch.zeros(n, dtype=torch.long, device=dev)
        self.segment_end = torch.full((n,), self.motion_num_frames, dtype=torch.long, device=dev)
        self.push_timer_s = torch.zeros(n, device=dev)
        self._ones = torch.ones(n, dtype=torch.bool, device=dev)
        self.rew_buf = torch.zeros(n, device=dev)
        self.episode_reward_terms = torch.zeros(n, len(self.reward_terms), device=dev)
        # Per-iteration statistics, accumulated on the device and read once per iteration (the
        # per-bin counts are the accounting's).
        self.stats_episodes = torch.zeros((), device=dev)
        self.stats_failures = torch.zeros((), device=dev)
        self.stats_length_sum = torch.zeros((), device=dev)
        self.stats_reward_sums = torch.zeros(len(self.reward_terms), device=dev)
        self.stats_terminations = torch.zeros(len(self.termination_terms), device=dev)
        self.stats_nonfinite = torch.zeros((), device=dev)
        self.stats_out_of_bounds = torch.zeros((), device=dev)
        self.stats_overflow = torch.zeros((), device=dev)
        self.stats_steps = torch.zeros((), device=dev)
        self.stats_errors = torch.zeros(3, device=dev)  # anchor pos m, body pos m, joint pos rad
        self.extras: dict = {"log": {}}
        self._actions_in = torch.zeros_like(self.actions)
        self._dones_long = torch.zeros(n, dtype=torch.long, device=dev)
        self._graphs = None
        self.reached_clip_end = torch.zeros(n, dtype=torch.bool, device=dev)

    def _uniform(self, shape, half_width) -> torch.Tensor:
        """U(-hw, hw); list half-widths are cached on the device (no host copies on the step path)."""
        if isinstance(half_width, (list, tuple)):
            key = tuple(float(x) for x in half_width)
            hw = self._half_widths.get(key)
            if hw is None:
                hw = self._half_widths[key] = torch.tensor(key, dtype=torch.float32, device=self.device)
        else:
            hw = float(half_width)
        u = torch.rand(shape, device=self.device)
        return (2.0 * u - 1.0) * hw

    def _randomize_startup(self) -> None:
        """Per-world model fields, written before graph capture (BeyondMimic ranges)."""
        r = self.cfg.randomization
        n = self.num_envs
        lo, hi = r.friction_range
        mu = lo + (hi - lo) * torch.rand(n, 1, device=self.device)
        friction = self.sim.geom_friction
        friction[:, self._foot_geoms, 0] = mu.expand(n, len(self._foot_geoms))
        self.sim.body_ipos[:, self._torso_body] += self._uniform((n, 3), list(r.torso_com_offset_m))
        self.default_joint_pos += self._uniform((n, self.num_actions), r.default_joint_offset_rad)
        self.push_timer_s[:] = self._draw_push_interval()

    def _draw_push_interval(self) -> torch.Tensor:
        lo, hi = self.cfg.randomization.push_interval_s
        return lo + (hi - lo) * torch.rand(self.num_envs, device=self.device)

    # ============================================================================ state
    def _compute_state(self) -> TrackingState:
        sim = self.sim
        ids = self.tracked_body_ids
        a = self.anchor_index
        f = self.time_steps.clamp(0, self.motion_num_frames - 1)
        root_quat = sim.qpos[:, 3:7]
        body_pos = sim.xpos[:, ids]
        body_quat = sim.xquat[:, ids]
        cvel = sim.cvel[:, ids]
        ang = cvel[..., 0:3]
        com = sim.subtree_com[:, self.root_body_id][:, None]
        lin = cvel[..., 3:6] + torch.cross(ang, body_pos - com, dim=-1)  # velocity of the body origin
        ref_pos = self.m_body_pos[f]
        ref_quat = self.m_body_quat[f]
        robot_anchor_pos, robot_anchor_quat = body_pos[:, a], body_quat[:, a]
        ref_anchor_pos, ref_anchor_quat = ref_pos[:, a], ref_quat[:, a]
        # Anchor-centred, yaw-aligned, height-preserving targets (BeyondMimic).
        delta_pos = torch.cat((robot_anchor_pos[:, :2], ref_anchor_pos[:, 2:3]), dim=-1)
        delta_rot = yaw_quat(quat_mul(robot_anchor_quat, quat_conj(ref_anchor_quat)))
        delta_rot_b = delta_rot[:, None].expand_as(ref_quat)
        rel_pos = delta_pos[:, None] + quat_apply(delta_rot_b, ref_pos - ref_anchor_pos[:, None])
        rel_quat = quat_mul(delta_rot_b, ref_quat)
        return TrackingState(
            joint_pos=sim.qpos[:, 7:],
            joint_vel=sim.qvel[:, 6:],
            root_lin_vel_b=quat_apply_inverse(root_quat, sim.qvel[:, 0:3]),
            root_ang_vel_b=sim.qvel[:, 3:6],
            robot_body_pos=body_pos,
            robot_body_quat=body_quat,
            robot_body_lin_vel=lin,
            robot_body_ang_vel=ang,
            robot_anchor_pos=robot_anchor_pos,
            robot_anchor_quat=robot_anchor_quat,
            ref_joint_pos=self.m_joint_pos[f],
            ref_joint_vel=self.m_joint_vel[f],
            ref_body_pos=ref_pos,
            ref_body_quat=ref_quat,
            ref_body_lin_vel=self.m_body_lin_vel[f],
            ref_body_ang_vel=self.m_body_ang_vel[f],
            ref_anchor_pos=ref_anchor_pos,
            ref_anchor_quat=ref_anchor_quat,
            ref_body_pos_relative=rel_pos,
            ref_body_quat_relative=rel_quat,
        )

    def _group(self, terms: _Terms, noisy: bool) -> torch.Tensor:
        parts = []
        for fn, params, cfg in zip(terms.funcs, terms.params, terms.cfgs):
            x = fn(self, **params)
            if noisy and cfg.noise > 0:
                x = x + self._uniform(x.shape, cfg.noise)
            parts.append(x)
        return torch.cat(parts, dim=-1)

    def _compute_observations(self) -> TensorDict:
        groups = {"policy": self._group(self.policy_terms, self.noise_enabled)}
        if len(self.critic_terms):
            groups["critic"] = self._group(self.critic_terms, False)
        return TensorDict(groups, batch_size=[self.num_envs], device=self.device)

    def undesired_contact_count(self) -> torch.Tensor:
        """Per world: contacts involving a robot body other than the end effectors."""
        sim = self.sim
        slots = torch.arange(sim.contact_worldid.shape[0], device=self.device)
        active = slots < sim.nacon
        geom = sim.contact_geom.long().clamp_min(0)
        bodies = self._geom_body[geom]
        hit = active & (self._undesired_body[bodies[:, 0]] | self._undesired_body[bodies[:, 1]])
        # Unused slots (most of the pool) add zero to worlds spread by slot number: sent all to one
        # world (their stale id), their atomic adds serialise (measured: 0.3 ms a step at 4096 envs).
        world = torch.where(active, sim.contact_worldid.long().clamp(0, self.num_envs - 1), slots % self.num_envs)
        return torch.zeros(self.num_envs, device=self.device).index_add_(0, world, hit.float())

    # ============================================================================ resets
    def _write_reference_state(self, mask: torch.Tensor, frames: torch.Tensor, noise: bool) -> None:
        """Put the masked envs at the reference state of `frames` (plus RSI noise when training)."""
        r = self.cfg.reset
        n = self.num_envs
        pos = self.m_root_pos[frames]
        quat = self.m_root_quat[frames]
        lin = self.m_root_lin_vel[frames]
        ang_w = self.m_root_ang_vel[frames]
        q = self.m_joint_pos[frames]
        qd = self.m_joint_vel[frames]
        if noise:
            pos = pos + self._uniform((n, 3), list(r.root_pos_range_m))
            rpy = self._uniform((n, 3), list(r.root_rot_range_rad))
            quat = quat_mul(quat_from_euler_xyz(rpy[:, 0], rpy[:, 1], rpy[:, 2]), quat)
            lin = lin + self._uniform((n, 3), list(r.root_lin_vel_range_mps))
            ang_w = ang_w + self._uniform((n, 3), list(r.root_ang_vel_range_radps))
            q = q + self._uniform(q.shape, r.joint_pos_range_rad)
            q = torch.minimum(torch.maximum(q, self.soft_joint_limits[:, 0]), self.soft_joint_limits[:, 1])
        qpos = torch.cat((pos, quat, q), dim=-1)
        qvel = torch.cat((lin, quat_apply_inverse(quat, ang_w), qd), dim=-1)  # free-joint angular vel is local
        m = mask[:, None]
        self.sim.qpos[:] = torch.where(m, qpos, self.sim.qpos)
        self.sim.qvel[:] = torch.where(m, qvel, self.sim.qvel)

    def _resample(self, mask: torch.Tensor, new_episode: torch.Tensor) -> None:
        """Masked envs start a new reference segment at a frame the sampler draws (RSI); those also
        in `new_episode` start a new episode there (a clip-end resample keeps the episode's start bin)."""
        bins = self.sampler.sample(self.num_envs)
        frames = self.layout.sample_frames(bins)
        frames = torch.where(mask, frames, self.time_steps)
        self.time_steps.copy_(frames)
        self.segment_start.copy_(torch.where(mask, frames, self.segment_start))
        self.segment_end.copy_(self.frame_clip_end[frames])
        self.accounting.start_episodes(mask & new_episode, bins)
        self._write_reference_state(mask, frames, noise=self.rsi_noise)

    def reset_to_frames(self, frames: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """Evaluation: put (masked) envs exactly at the reference state of `frames`, episode counters 0."""
        mask = self._ones if mask is None else mask
        frames = frames.to(self.device).long()
        self.time_steps.copy_(torch.where(mask, frames, self.time_steps))
        self.segment_start.copy_(self.time_steps)
        self.segment_end.copy_(self.frame_clip_end[self.time_steps])
        self._write_reference_state(mask, self.time_steps, noise=False)
        self.episode_length_buf.masked_fill_(mask, 0)
        self.actions.masked_fill_(mask[:, None], 0.0)
        self.last_actions.masked_fill_(mask[:, None], 0.0)
        self.sim.forward_kinematics()
        self._observe()

    # ============================================================================ VecEnv API
    def get_observations(self) -> TensorDict:
        return self._obs.clone()

    def step(self, actions: torch.Tensor):
        self._actions_in.copy_(actions)
        if self._graphs is not None:
            pre, post, obs = self._graphs
            pre.replay()
            self.sim.step()
            post.replay()
            self.sim.forward_kinematics()
            obs.replay()
        else:
            self._pre_physics()
            self.sim.step()
            self._post_physics()
            if self.mode == "train":
                self.sim.forward_kinematics()
            self._observe()
        # A copy: rsl-rl keeps a reference to the observation it acted on until the transition is
        # stored after the next step, and the graphs overwrite `_obs` in place.
        return self._obs.clone(), self.rew_buf, self._dones_long, self.extras

    def _pre_physics(self) -> None:
        self.last_actions.copy_(self.actions)
        self.actions.copy_(self._actions_in)
        self.sim.ctrl.copy_(self.default_joint_pos + self.action_scale * self.actions)

    def _post_physics(self) -> None:
        """Terminations, rewards, sampler and resets: everything between physics and kinematics."""
        sim = self.sim
        self.episode_length_buf += 1
        # Worlds that blew up (non-finite, or finite but beyond physical bounds) are reset, truncated
        # (never charged to the sampler as failures) and counted, all on the device.
        nonfinite = sim.nonfinite_worlds()
        out_of_bounds = sim.out_of_bounds_worlds() & ~nonfinite
        sim.sanitize(nonfinite | out_of_bounds)
        self.stats_overflow += sim.overflowed_worlds().sum()
        sim.clear_overflow()

        self.state = self._compute_state()
        term_flags = torch.stack(
            [fn(self, **p) for fn, p in zip(self.termination_terms.funcs, self.termination_terms.params)], dim=-1
        )
        rewards = torch.stack(
            [fn(self, **p) for fn, p in zip(self.reward_terms.funcs, self.reward_terms.params)], dim=-1
        ) * (self.reward_weights * self.step_dt)
        nonfinite = nonfinite | ~torch.isfinite(rewards).all(-1)
        out_of_bounds = (out_of_bounds | (rewards.sum(-1).abs() > self._max_abs_reward)) & ~nonfinite
        self.stats_nonfinite += nonfinite.sum()
        self.stats_out_of_bounds += out_of_bounds.sum()
        nonfinite = nonfinite | out_of_bounds  # from here on: every world that is reset as broken
        rewards = torch.where(nonfinite[:, None], 0.0, rewards)
        truncated = (term_flags & self._timeout_term).any(-1) | nonfinite
        terminated = (term_flags & ~self._timeout_term).any(-1) & ~nonfinite
        self.rew_buf = rewards.sum(-1)
        self.episode_reward_terms += rewards
        dones = terminated | truncated
        self._accumulate_step_stats(term_flags)

        if self.mode == "train":
            self._accumulate_episode_stats(dones, terminated)
            # What ends now, counted in one pass: finished episodes (at this frame) and, for
            # attribution=failure, continuing episodes whose clip ends on the next frame (never failed).
            next_frame = self.time_steps + 1
            clip_end = (next_frame >= self.segment_end) & ~dones
            counts = self.accounting.count(dones, clip_end, torch.where(dones, self.time_steps, next_frame),
                                           self.segment_start, terminated, nonfinite, self.episode_length_buf)
            self._resample(dones, dones)
            self.episode_length_buf.masked_fill_(dones, 0)
            self.actions.masked_fill_(dones[:, None], 0.0)
            self.last_actions.masked_fill_(dones[:, None], 0.0)
            self.episode_reward_terms.masked_fill_(dones[:, None], 0.0)
            self.time_steps += 1
            # End of the clip mid-episode: resample and teleport; the episode continues. This also
            # catches a reset that started on the clip's last frame: that episode has not tracked a
            # frame yet, so it starts (and counts for) the bin drawn now.
            self._resample(self.time_steps >= self.segment_end, dones)
            # After this step's resets were drawn, as in the released code: the sampler update
            # (update_every=step), or the counts wait for end_rollout (update_every=iteration).
            self.accounting.record(counts)
            if self.randomize:
                self._push(self.step_dt)
        else:
            self.time_steps.copy_(torch.minimum(self.time_steps + 1, self.segment_end - 1))
            self.reached_clip_end = self.time_steps >= self.segment_end - 1
            if self.randomize:  # robust evaluation
                self._push(self.step_dt)
                self.sim.forward_kinematics()
        self._dones_long = dones.long()
        self.extras = {"time_outs": truncated, "log": {}, "terminated": terminated}

    def _observe(self) -> None:
        self.state = self._compute_state()
        self._obs = self._compute_observations()

    def capture(self) -> None:
        """Record the torch work of a step as three CUDA graphs around the simulator's graphs.

        Everything on the step path has fixed shapes and no host synchronisation, so it can be
        replayed; this removes the per-kernel launch cost that otherwise dominates at 4096+ envs.
        With `sim.compile_env_step` the three parts are first fused by torch.compile (fewer, larger
        kernels in the graphs). Two warm-up steps (compiling, filling caches) run first; their
        statistics are discarded.
        """
        if not (self.device.type == "cuda" and self.sim.use_graph):
            return
        # Under torchrun the graph also holds the NCCL all-reduce of the sampler counts: the
        # warm-up steps create the communicator before capture, as NCCL capture requires.
        parts = self._warmed_up_parts()
        pool = torch.cuda.graph_pool_handle()
        graphs = []
        for fn in parts:
            g = torch.cuda.CUDAGraph()
            with torch.cuda.graph(g, pool=pool):
                fn()
            graphs.append(g)
        self._graphs = tuple(graphs)
        self.accounting.discard()
        self.pop_iteration_stats()

    def _warmed_up_parts(self) -> tuple:
        """(pre, post, obs), compiled when `sim.compile_env_step` and compilation works, after the
        warm-up steps that capture needs."""
        parts = (self._pre_physics, self._post_physics, self._observe)
        if self.sim.cfg.compile_env_step:
            compiled = tuple(torch.compile(fn, dynamic=False) for fn in parts)
            try:
                self._warm_up(compiled)
                return compiled
            except Exception as e:  # a missing or broken compiler toolchain costs speed, not the run
                log.warning("sim.compile_env_step: torch.compile failed (%s: %s); capturing the step "
                            "uncompiled", type(e).__name__, str(e).splitlines()[0] if str(e) else "")
        self._warm_up(parts)
        return parts

    def _warm_up(self, parts) -> None:
        """Two steps through (pre, post, obs) outside capture: compiles, allocates, creates the
        NCCL communicator under torchrun."""
        pre, post, obs = parts
        self._actions_in.zero_()
        for _ in range(2):
            pre()
            self.sim.step()
            post()
            self.sim.forward_kinematics()
            obs()
        torch.cuda.synchronize(self.device)

    # ============================================================================ sampler & stats
    def end_rollout(self) -> None:
        """Once per PPO iteration, after the rollout: the sampler update of update_every=iteration
        (the design's runner hook); the sampling distribution is fixed until then."""
        if self.accounting is not None:
            self.accounting.end_rollout()

    def _accumulate_episode_stats(self, dones: torch.Tensor, terminated: torch.Tensor) -> None:
        d = dones.float()
        self.stats_episodes += d.sum()
        self.stats_failures += terminated.float().sum()
        self.stats_length_sum += (self.episode_length_buf.float() * d).sum()
        self.stats_reward_sums += (self.episode_reward_terms * d[:, None]).sum(0)

    def _accumulate_step_stats(self, term_flags: torch.Tensor) -> None:
        s = self.state
        self.stats_steps += 1
        self.stats_terminations += term_flags.float().sum(0)
        self.stats_errors[0] += (s.ref_anchor_pos - s.robot_anchor_pos).norm(dim=-1).mean()
        self.stats_errors[1] += (s.ref_body_pos_relative - s.robot_body_pos).norm(dim=-1).mean()
        self.stats_errors[2] += (s.ref_joint_pos - s.joint_pos).abs().mean()

    def _push(self, dt: float) -> None:
        r = self.cfg.randomization
        self.push_timer_s -= dt
        due = self.push_timer_s <= 0
        n = self.num_envs
        dv = self._uniform((n, 3), list(r.push_lin_vel_mps))
        dw = quat_apply_inverse(self.sim.qpos[:, 3:7], self._uniform((n, 3), list(r.push_ang_vel_radps)))
        push = torch.cat((dv, dw), dim=-1) * due[:, None]
        self.sim.qvel[:, 0:6] += push
        self.push_timer_s.copy_(torch.where(due, self._draw_push_interval(), self.push_timer_s))

    def pop_iteration_stats(self) -> dict:
        """Per-iteration statistics (one host transfer), then reset the accumulators."""
        steps = max(float(self.stats_steps), 1.0)
        if self.accounting is not None:
            bin_episodes, bin_failures = self.accounting.pop_counts()
        else:
            bin_episodes = bin_failures = np.zeros(self.layout.num_bins)
        out = {
            # Per bin, as the sampler was fed them (after end_rollout for update_every=iteration).
            "bin_episodes": bin_episodes,
            "bin_failures": bin_failures,
            "nonfinite_resets": float(self.stats_nonfinite),
            "out_of_bounds_resets": float(self.stats_out_of_bounds),
            "overflow_worlds": float(self.stats_overflow),
        }
        episodes = float(self.stats_episodes)
        out["episodes"] = episodes
        out["failures"] = float(self.stats_failures)
        out["mean_episode_length"] = float(self.stats_length_sum) / episodes if episodes else float("nan")
        sums = (self.stats_reward_sums / max(episodes, 1.0)).cpu().numpy()
        for name, v in zip(self.reward_terms.names, sums):
            out[f"Episode_Reward/{name}"] = float(v) if episodes else float("nan")
        out["mean_episode_reward"] = float(sums.sum()) if episodes else float("nan")
        terms = (self.stats_terminations / (steps * self.num_envs)).cpu().numpy()
        for name, v in zip(self.termination_terms.names, terms):
            out[f"Episode_Termination/{name}"] = float(v)
        errs = (self.stats_errors / steps).cpu().numpy()
        out["Metrics/error_anchor_pos_m"] = float(errs[0])
        out["Metrics/error_body_pos_m"] = float(errs[1])
        out["Metrics/error_joint_pos_rad"] = float(errs[2])
        for buf in (
            self.stats_terminations, self.stats_errors,
            self.stats_nonfinite, self.stats_out_of_bounds, self.stats_overflow, self.stats_steps, self.stats_episodes,
            self.stats_failures, self.stats_length_sum, self.stats_reward_sums,
        ):
            buf.zero_()
        return out

    def close(self) -> None:
        """Release the captured graphs. Under torchrun this must precede destroy_process_group: a
        live graph holding an NCCL all-reduce makes it hang (pytorch/pytorch#115388)."""
        if self._graphs is not None:
            torch.cuda.synchronize(self.device)
            self._graphs = None


__all__ = ["TrackingEnv", "TrackingState"]
