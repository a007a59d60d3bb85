"""The policy networks as rsl-rl builds them: the `train_cfg` of a PPO config, and the deterministic
actor rebuilt from a checkpoint (eval, play, export)."""

from __future__ import annotations

from pathlib import Path

from bmimic.training.checkpoints import CheckpointMismatchError, mismatch_detail


def rsl_rl_train_cfg(ppo, run_name: str) -> dict:
    """The rsl-rl-lib 5.5 `train_cfg` dict for a PPOConfig."""
    return {
        "num_steps_per_env": ppo.num_steps_per_env,
        "save_interval": ppo.save_interval,
        "obs_groups": {"actor": ["policy"], "critic": list(ppo.critic_obs_groups)},
        "run_name": run_name,
        "check_for_nan": False,  # a host sync per step; the env resets non-finite worlds itself
        "torch_compile_mode": ppo.torch_compile_mode,
        "logger": "tensorboard",
        "algorithm": {
            "class_name": "bmimic.training.ppo:GraphPPO",
            "cuda_graphs": ppo.cuda_graphs,
            "learning_rate": ppo.learning_rate,
            "num_learning_epochs": ppo.num_learning_epochs,
            "num_mini_batches": ppo.num_mini_batches,
            "schedule": ppo.schedule,
            "desired_kl": ppo.desired_kl,
            "clip_param": ppo.clip_param,
            "entropy_coef": ppo.entropy_coef,
            "value_loss_coef": ppo.value_loss_coef,
            "use_clipped_value_loss": ppo.use_clipped_value_loss,
            "gamma": ppo.gamma,
            "lam": ppo.lam,
            "max_grad_norm": ppo.max_grad_norm,
            "normalize_advantage_per_mini_batch": ppo.normalize_advantage_per_mini_batch,
            "rnd_cfg": None,
            "symmetry_cfg": None,
        },
        "actor": {
            "class_name": "MLPModel",
            "hidden_dims": list(ppo.actor_hidden_dims),
            "activation": ppo.activation,
            "obs_normalization": ppo.obs_normalization,
            "distribution_cfg": {
                "class_name": "GaussianDistribution",
                "init_std": ppo.init_noise_std,
                "std_type": ppo.noise_std_type,
            },
        },
        "critic": {
            "class_name": "MLPModel",
            "hidden_dims": list(ppo.critic_hidden_dims),
            "activation": ppo.activation,
            "obs_normalization": ppo.obs_normalization,
        },
    }


def build_policy(state: dict, env, ppo_cfg, device: str, checkpoint: Path | str = "checkpoint"):
    """The deterministic actor (rsl-rl MLPModel) built as the Trainer builds it, weights from `state`."""
    from rsl_rl.utils import resolve_class

    train_cfg = rsl_rl_train_cfg(ppo_cfg, "eval")
    actor_class, actor_kwargs = resolve_class(train_cfg["actor"])
    actor = actor_class(env.get_observations(), train_cfg["obs_groups"], "actor", env.num_actions, **actor_kwargs)
    try:
        actor.load_state_dict(state["actor_state_dict"], strict=True)
    except RuntimeError as e:
        raise CheckpointMismatchError(
            f"{checkpoint}: its actor does not match this run's config (ppo.actor_hidden_dims="
            f"{list(ppo_cfg.actor_hidden_dims)}, {actor.obs_dim} policy observations, {env.num_actions} "
            f"actions): {mismatch_detail(e)}"
        ) from None
    return actor.to(device).eval()

