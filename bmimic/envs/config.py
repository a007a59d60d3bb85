"""Schema of the `env` config group: the tracking MDP as named term functions with parameters.

Every observation, reward, termination term names a plain function in `bmimic.envs.mdp`
(or `package.module:function`) with its parameters, so an ablation of the MDP is a config override:
`env.rewards.action_rate.weight=0`, `env.terminations.ee_body_pos.params.threshold_m=0.3`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List


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
    """Weight; the step reward is sum(weight * term) * step_dt, as in BeyondMimic. 0 disables the term."""
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
class RandomizationConfig:
    """Per-world domain randomisation (BeyondMimic ranges, notes section 3.6)."""

    enabled: bool = True
    """Master switch (evaluation and play turn it off)."""
    friction_range: List[float] = field(default_factory=lambda: [0.3, 1.6])
    """Range of the sliding friction coefficient of the foot geoms, drawn per world."""
    torso_com_offset_m: List[float] = field(default_factory=lambda: [0.025, 0.05, 0.05])
    """Half-widths of the torso_link centre-of-mass offset along x, y, z."""
    default_joint_offset_rad: float = 0.01
    """Half-width of a per-world calibration offset added to the default joint pose (and action offset)."""
    push_interval_s: List[float] = field(default_factory=lambda: [1.0, 3.0])
    """Range of the time between velocity pushes, drawn per world after each push."""
    push_lin_vel_mps: List[float] = field(default_factory=lambda: [0.5, 0.5, 0.2])
    """Half-widths of the root linear velocity change of a push."""
    push_ang_vel_radps: List[float] = field(default_factory=lambda: [0.52, 0.52, 0.78])
    """Half-widths of the root angular velocity change of a push."""


@dataclass
class EnvConfig:
    """The BeyondMimic tracking MDP (notes section 3)."""

    episode_length_s: float = 10.0
    """Episode length; reaching it is a time-out (truncation)."""
    max_abs_step_reward: float = 1.0e6
    """A world whose step reward is larger than this in magnitude (or not finite) is reset and counted,
    its reward zeroed: one broken world must never reach the value loss."""
    observation_noise: bool = True
    """Corrupt the policy group with each term's uniform noise during training."""
    policy_observations: Dict[str, ObsTermConfig] = field(default_factory=dict)
    """Terms of the `policy` group, concatenated in this order (BeyondMimic: 160 dims)."""
    critic_observations: Dict[str, ObsTermConfig] = field(default_factory=dict)
    """Terms of the privileged `critic` group, never corrupted (BeyondMimic: 286 dims)."""
    rewards: Dict[str, RewardTermConfig] = field(default_factory=dict)
    """Reward terms; each is logged separately under Episode_Reward/<name>."""
    terminations: Dict[str, TerminationTermConfig] = field(default_factory=dict)
    """Termination terms; each is logged separately under Episode_Termination/<name>."""
    reset: ResetConfig = field(default_factory=ResetConfig)
    """Reference-state initialisation noise."""
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    """Domain randomisation and pushes."""
