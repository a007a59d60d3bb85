"""The BeyondMimic motion-tracking environment as an rsl-rl-lib `VecEnv` over the batched simulator.

`TrackingEnv` coordinates one control step; the work is done by its parts, all batched on the
device, with fixed shapes and no host synchronisation:
  1. actions -> PD targets (`ctrl`), `decimation` physics steps + kinematics (`bmimic.sim`);
  2. broken worlds are reset, the state is computed once (`state.compute_state`), then the
     termination and reward managers (`managers/`) evaluate their terms;
  3. finished episodes are counted per bin (`bmimic.sampling.feedback`), finished envs restart
     at frames the sampler draws (`resets`: reference-state initialisation), every env advances one
     frame and envs past the end of their clip are resampled without ending the episode
     (`segments`); the counts go to the sampler; the event manager runs reset and interval events
     (pushes);
  4. kinematics are recomputed after those state writes (no stale poses, cf. mjlab #1068) and the
     observation manager builds the observations from a fresh state.
On a GPU the torch parts of 1, 2-3 and 4 are captured as CUDA graphs (`graphs.StepGraphs`).
"""

from __future__ import annotations

from typing import cast

import mujoco
import torch
from omegaconf import DictConfig, OmegaConf
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from bmimic import BmimicError
from bmimic.envs.bodies import TrackedBodies
from bmimic.envs.config import EnvConfig, episode_length_steps
from bmimic.envs.episodes import Episodes, PlacedEpisodes, SampledEpisodes
from bmimic.envs.graphs import StepGraphs
from bmimic.envs.managers import EventManager, ObservationManager, RewardManager, TerminationManager
from bmimic.envs.noise import UniformNoise
from bmimic.envs.resets import write_reference_state
from bmimic.envs.segments import ReferenceSegments
from bmimic.envs.state import compute_state
from bmimic.envs.stats import IterationStats
from bmimic.motion.reference import ReferenceMotion
from bmimic.robot import RobotInfo
from bmimic.sampling.bins import Layout
from bmimic.sampling.feedback import SamplerFeedback
from bmimic.sim import SimConfig, Simulator


class TrackingEnv(VecEnv):
    """BeyondMimic tracking of a reference motion (one clip or a library of clips) by `num_envs` robots.

    `mode="train"`: event terms (domain randomisation, pushes), observation noise and automatic
    resets at frames the sampler of `feedback` draws. `mode="eval"`: none of those; the caller places
    envs with `reset_to_frames` and reads terminations, and the reference stops at the end of each
    clip. `robust=True` (eval only) turns events and observation noise back on, as in training.
    `layout` (eval only) is recorded for the exported metadata. The difference lives in one object,
    `self.episodes` (SampledEpisodes or PlacedEpisodes, above); the env never branches on its mode.
    """

    def __init__(self, env_cfg: EnvConfig, sim_cfg: SimConfig, mjm: mujoco.MjModel, robot: RobotInfo,
                 reference: ReferenceMotion, num_envs: int, device: str, feedback: SamplerFeedback | None = None,
                 mode: str = "train", robust: bool = False, layout: Layout | None = None) -> None:
        if mode not in ("train", "eval"):
            raise ValueError(f"mode must be train or eval, got {mode!r}")
        if (mode == "train") != (feedback is not None):
            raise ValueError("a training environment needs the sampler's feedback; an evaluation one takes none")
        if robust and mode == "train":
            raise ValueError("robust is an evaluation's option: a training environment is always perturbed")
        self.episodes: Episodes = SampledEpisodes(feedback) if feedback is not None else PlacedEpisodes(robust, layout)
        # Plain dataclasses, not OmegaConf nodes: the step reads config fields every call, and plain
        # attribute access is cheaper and can be traced by torch.compile.
        self.cfg = cfg = cast(EnvConfig, OmegaConf.to_object(env_cfg)) if isinstance(env_cfg, DictConfig) else env_cfg
        self.num_envs, self.device = num_envs, torch.device(device)  # the mode lives in self.episodes
        perturbed = self.episodes.perturbed
        self.feedback, self.reference, self.robot = feedback, reference, robot
        self.layout = self.episodes.layout
        """The bin layout (training: the feedback's; evaluation: for the exported metadata only)."""
        self.segments = seg = ReferenceSegments(reference, sim_cfg, num_envs, self.device)
        self.bodies = TrackedBodies(mjm, robot, self.device)
        if reference.body_names != [robot.body_names[int(i) - 1] for i in robot.tracked_body_ids]:
            raise BmimicError("motion: the reference tracks other bodies than robot.tracked_bodies")
        self.uniform = UniformNoise(self.device)
        self.events = EventManager(cfg.events if perturbed and cfg.events_enabled else {}, num_envs, self.device)
        self.sim = Simulator(mjm, sim_cfg, num_envs, device, randomized_fields=self.events.model_fields)
        self.step_dt = self.sim.control_dt
        self.max_episode_length = episode_length_steps(cfg, sim_cfg)
        self.num_actions = len(robot.joint_names)
        t = lambda x: torch.as_tensor(x, dtype=torch.float32, device=self.device)  # noqa: E731
        self.action_scale, self.nominal_joint_pos = t(robot.action_scale), t(robot.default_joint_pos)
        self.default_joint_pos = self.nominal_joint_pos.repeat(num_envs, 1)
        """Per world: the action offset and the joint observation's origin (events may offset it)."""
        self.soft_joint_limits = t(robot.soft_joint_limits)
        self.gravity_w = t([[0.0, 0.0, -1.0]])
        self.observations = ObservationManager(
            {"policy": (cfg.policy_observations, perturbed and cfg.observation_noise),
             "critic": (cfg.critic_observations, False)}, self.uniform, num_envs, self.device)
        self.rewards = RewardManager(cfg.rewards, self.step_dt, num_envs, self.device)
        self.terminations = TerminationManager(cfg.terminations, self.device)
        self.stats = IterationStats(self.device)
        # The reference frames by their usual names (the same tensors, written in place).
        self.time_steps, self.segment_start, self.segment_end = seg.time_steps, seg.segment_start, seg.segment_end
        self.reached_clip_end = seg.reached_clip_end
        self.episode_length_buf = torch.zeros(num_envs, dtype=torch.long, device=self.device)
        self.actions = torch.zeros(num_envs, self.num_actions, device=self.device)
        self.last_actions = torch.zeros_like(self.actions)
        self._actions_in = torch.zeros_like(self.actions)
        self._ones = torch.ones(num_envs, dtype=torch.bool, device=self.device)
        self.rew_buf = torch.zeros(num_envs, device=self.device)
        self._dones_long = torch.zeros(num_envs, dtype=torch.long, device=self.device)
        self.extras: dict = {}
        self._graphs: StepGraphs | None = None
        self.events.startup(self)  # per-world model fields and the first push times, before capture
        self.sim.capture()
        self.episodes.begin(self)
        self.sim.forward_kinematics()
        self._observe()
        if feedback is not None and self.device.type == "cuda" and self.sim.use_graph:  # training
            # Captured steps recompute kinematics after every step (StepGraphs), as training needs.
            self._actions_in.zero_()
            self._graphs = StepGraphs((self._pre_physics, self._post_physics, self._observe), self.sim,
                                      self.sim.cfg.compile_env_step)
            feedback.discard()  # the warm-up steps' counts and statistics
            self.pop_iteration_stats()

    # ----------------------------------------------------------------------------------- resets
    def reset_to_frames(self, frames: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """Evaluation: put (masked) envs exactly at the reference state of `frames`, episode counters 0."""
        mask = self._ones if mask is None else mask
        frames = self.segments.start(mask, frames.to(self.device).long())
        write_reference_state(self.sim, self.reference, mask, frames)
        # A placed world starts cold, as a fresh one would: its result never depends on earlier waves.
        self.sim.qacc_warmstart.masked_fill_(mask[:, None], 0.0)
        self.events.reset(self, mask)
        self.episode_length_buf.masked_fill_(mask, 0)
        self.actions.masked_fill_(mask[:, None], 0.0)
        self.last_actions.masked_fill_(mask[:, None], 0.0)
        self.sim.forward_kinematics()
        self._observe()

    def redraw_startup_events(self) -> None:
        """Evaluation: every world draws its startup events (domain randomisation of the model and the
        default pose, the first push times) anew from the nominal model, as a fresh environment would;
        the caller then places the worlds with `reset_to_frames`."""
        if not self.episodes.places_worlds:
            raise ValueError("redraw_startup_events is for an evaluation environment between its waves")
        self.sim.restore_model_fields(self.events.model_fields)
        self.default_joint_pos.copy_(self.nominal_joint_pos.expand_as(self.default_joint_pos))
        self.events.startup(self)

    # ----------------------------------------------------------------------------------- VecEnv API
    @property
    def perturbed(self) -> bool:
        """Events and observation noise on: training, and a robust evaluation (runs.schema.CONDITIONS)."""
        return self.episodes.perturbed

    def get_observations(self) -> TensorDict:
        return self._obs.clone()

    def observation_dims(self) -> dict[str, int]:
        """Width of each observation group (what a checkpoint must match), without copying them."""
        return {str(k): int(v.shape[-1]) for k, v in self._obs.items()}

    def step(self, actions: torch.Tensor):
        self._actions_in.copy_(actions)
        if self._graphs is not None:
            self._graphs.replay()
        else:
            self._pre_physics()
            self.sim.step()
            self._post_physics()
            if self.episodes.kinematics_after_step(self):
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
        self.episode_length_buf += 1
        # Worlds that blew up (non-finite, or finite but beyond physical bounds) are reset, truncated
        # for PPO (no bootstrap from a blown-up state), counted, and charged to the sampler and the
        # iteration's failure rate as failures, all on the device.
        nonfinite, out_of_bounds, overflowed = self.sim.reset_broken_worlds()
        self.state = compute_state(self.sim, self.reference, self.bodies, self.time_steps)
        flags = self.terminations.compute(self)
        rewards = self.rewards.compute(self)
        nonfinite = nonfinite | ~torch.isfinite(rewards).all(-1)
        out_of_bounds = (out_of_bounds | (rewards.sum(-1).abs() > self.cfg.max_abs_step_reward)) & ~nonfinite
        self.stats.broken(nonfinite, out_of_bounds, overflowed)
        broken = nonfinite | out_of_bounds
        rewards = torch.where(broken[:, None], 0.0, rewards)
        truncated = self.terminations.time_outs(flags) | broken
        terminated = self.terminations.terminations(flags) & ~broken
        self.rew_buf = rewards.sum(-1)
        self.rewards.accumulate(rewards)
        self.stats.step(self.state)
        dones = terminated | truncated
        self.episodes.end_step(self, dones, terminated, broken)
        self._dones_long = dones.long()
        # `broken` (a time-out for PPO's bootstrap) lets the evaluator count a broken world as a failure.
        self.extras = {"time_outs": truncated, "terminated": terminated, "broken": broken}

    def _observe(self) -> None:
        self.state = compute_state(self.sim, self.reference, self.bodies, self.time_steps)
        self._obs = self.observations.compute(self)

    # ----------------------------------------------------------------------------------- per iteration
    def end_rollout(self) -> None:
        """Once per PPO iteration, after the rollout: the sampler update of update_every=iteration
        (the design's runner hook); the sampling distribution is fixed until then."""
        self.episodes.end_rollout()

    def pop_iteration_stats(self) -> dict:
        """Per-iteration statistics (one host transfer each), then reset the accumulators."""
        bin_episodes, bin_failures = self.episodes.pop_counts()
        counts, metrics, steps = self.stats.pop()
        return {"bin_episodes": bin_episodes, "bin_failures": bin_failures, **counts,
                **self.rewards.pop_log(counts["episodes"]), **self.terminations.pop_log(steps, self.num_envs),
                **metrics}

    def close(self) -> None:
        """Release the captured graphs. Under torchrun this must precede destroy_process_group."""
        if self._graphs is not None:
            self._graphs.release()
            self._graphs = None


__all__ = ["Episodes", "PlacedEpisodes", "SampledEpisodes", "TrackingEnv", "episode_length_steps"]
