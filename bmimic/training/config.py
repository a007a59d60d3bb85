"""Schemas of the `ppo` and `eval` config groups."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional


@dataclass
class PPOConfig:
    """rsl-rl-lib 5.5 PPO settings; defaults are BeyondMimic's (notes section 5)."""

    num_steps_per_env: int = 24
    """Rollout length per env and iteration (4096 x 24 = 98,304 samples per iteration)."""
    max_iterations: int = 30000
    """Training iterations used on a GPU when the top-level `max_iterations` is null."""
    save_interval: int = 500
    """Write a checkpoint (and ONNX export) every this many iterations, and at the end."""
    init_at_random_ep_len: bool = True
    """Randomise the initial episode counters so time-outs do not arrive in lockstep."""
    learning_rate: float = 1.0e-3
    """Adam learning rate (initial value under the adaptive schedule)."""
    schedule: str = "adaptive"
    """`adaptive` (KL-driven) or `fixed` learning rate."""
    desired_kl: float = 0.01
    """Target KL divergence of the adaptive schedule."""
    num_learning_epochs: int = 5
    """Passes over the rollout per iteration."""
    num_mini_batches: int = 4
    """Mini-batches per epoch; num_envs * num_steps_per_env must be divisible by it."""
    clip_param: float = 0.2
    """PPO ratio clip."""
    entropy_coef: float = 0.005
    """Entropy bonus coefficient."""
    value_loss_coef: float = 1.0
    """Value loss coefficient."""
    use_clipped_value_loss: bool = True
    """Clip the value update like the policy ratio."""
    gamma: float = 0.99
    """Discount factor."""
    lam: float = 0.95
    """GAE lambda."""
    max_grad_norm: float = 1.0
    """Gradient norm clip."""
    normalize_advantage_per_mini_batch: bool = False
    """Normalise advantages per mini-batch instead of over the whole rollout."""
    actor_hidden_dims: List[int] = field(default_factory=lambda: [512, 256, 128])
    """Actor MLP hidden layer sizes."""
    critic_hidden_dims: List[int] = field(default_factory=lambda: [512, 256, 128])
    """Critic MLP hidden layer sizes."""
    activation: str = "elu"
    """Hidden activation of both MLPs."""
    init_noise_std: float = 1.0
    """Initial standard deviation of the Gaussian policy."""
    noise_std_type: str = "scalar"
    """`scalar` or `log` parameterisation of the policy std."""
    obs_normalization: bool = True
    """Empirical observation normalisation for actor and critic."""
    critic_obs_groups: List[str] = field(default_factory=lambda: ["critic"])
    """Observation groups the critic sees (BeyondMimic: only the privileged `critic` group)."""
    cuda_graphs: bool = True
    """On a GPU, replay the policy's action sampling and each PPO mini-batch step from CUDA graphs
    (the same computation as rsl-rl's PPO, without its per-mini-batch host reads); CPU ignores it."""
    float32_matmul_precision: str = "high"
    """torch.set_float32_matmul_precision for the policy and value networks: `high` (TF32 tensor
    cores on Ampere+ GPUs; the PPO update at 4096 envs on an H100 takes 0.040 s instead of 0.063 s,
    learning curves matched FP32 in an A/B run, docs/benchmarks.md), `highest` (full FP32) or
    `medium` (bf16). No effect on a CPU."""
    torch_compile_mode: Optional[str] = None
    """torch.compile mode for actor/critic (null disables; `default`, `max-autotune-no-cudagraphs`)."""


@dataclass
class EvalConfig:
    """Sampler-independent evaluation: episodes started at stratified frames of every bin."""

    every_iters: int = 250
    """Evaluate every this many training iterations (0: only at the end). Always evaluates at the end."""
    episodes_per_bin: Optional[int] = None
    """Episodes started per bin, at evenly spaced frames inside it; null: 32 on a GPU (a failure rate
    resolved to 1/32), 1 on a CPU (smoke runs)."""
    horizon_s: float = 2.0
    """An episode that survives this long (or reaches the end of the motion) counts as a success."""
    max_envs: int = 8192
    """Upper bound on simultaneous evaluation worlds; larger evaluations run in several waves."""
    max_mpkpe_rel_mm: Optional[float] = None
    """When set, an episode whose mean root-relative MPKPE (mm) exceeds it fails too ("tracked", not only
    "did not fall"); null: only terminations are failures."""
    robust: bool = False
    """At the end of the run, evaluate again with domain randomisation, observation noise and pushes on
    (eval_robust.parquet; `final_robust_eval_*` in metrics.json)."""
