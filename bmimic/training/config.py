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
class WholeClipConfig:
    """Whole-clip evaluation: rollouts from each clip's first frame to its last (bmimic.training.whole_clip)."""

    rollouts: Optional[int] = None
    """Rollouts per clip under a perturbed condition (`robust`), each with its own draw of domain
    randomisation, pushes and observation noise; null: 128 on a GPU (one wave is latency-bound, so more
    rollouts cost little there), 2 on a CPU. The `nominal` condition is deterministic (every rollout
    from a clip's first frame would be the same), so it runs one per clip."""
    conditions: List[str] = field(default_factory=lambda: ["nominal", "robust"])
    """Which conditions to evaluate: `nominal` (as the window evaluation: no domain randomisation, no
    observation noise, no pushes) and/or `robust` (training's domain randomisation, observation noise and
    pushes)."""
    every_iters: int = 0
    """During training, evaluate whole clips after every this many iterations (a multiple of
    eval.every_iters: it runs right after that window evaluation); 0: not on a fixed cadence."""
    max_share: Optional[float] = None
    """During training, also evaluate whole clips after a window evaluation whenever all evaluations so far,
    this one included at the duration of the last one, took at most this share of the wall time since the
    first iteration (bmimic.race: 0.10); null: off."""
    after_success: Optional[float] = None
    """Start the cadence (every_iters, max_share) only once a window evaluation reached this evaluated
    success (bmimic.race: 0.95): an earlier policy fails whole clips anyway; null: from the start."""
    at_end: bool = False
    """Evaluate whole clips once more at the end of training (`final_whole_clip_*` in metrics.json)."""
    max_clip_s: float = 600.0
    """The longest clip a whole-clip evaluation runs (seconds): a longer clip is refused in one line,
    never cut short. One rollout is the clip's length in sequential control steps (on one H200, 131.5 s
    of clip took 51 s), so this bounds one evaluation's wall time."""


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
    whole_clip: WholeClipConfig = field(default_factory=WholeClipConfig)
    """Whole-clip evaluation (whole_clip*.parquet during training; `python -m bmimic.eval --whole-clip`)."""


def launch_end_iteration(max_iterations: int, stop_at_iteration: int | None) -> int:
    """The iteration a launch trains to: max_iterations, or stop_at_iteration when it pauses earlier (the
    run's budget, and every schedule spanning it, stay max_iterations)."""
    return min(int(max_iterations), int(stop_at_iteration)) if stop_at_iteration else int(max_iterations)
