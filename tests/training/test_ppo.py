"""GraphPPO computes rsl-rl's PPO update: same parameters, normalisers, losses and learning rate."""

from __future__ import annotations

import pytest
import torch
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from bmimic.training.ppo import GraphPPO

N, T, A = 16, 6, 3  # envs, steps per rollout, actions


def _obs(gen: torch.Generator, device: str) -> TensorDict:
    return TensorDict({"policy": torch.randn(N, 7, generator=gen).to(device),
                       "critic": torch.randn(N, 9, generator=gen).to(device)}, batch_size=[N], device=device)


def _make(cls, device: str, **kw):
    obs = _obs(torch.Generator().manual_seed(0), device)
    groups = {"actor": ["policy"], "critic": ["critic"]}
    torch.manual_seed(0)
    actor = MLPModel(obs, groups, "actor", A, hidden_dims=[32, 16], obs_normalization=True,
                     distribution_cfg={"class_name": "GaussianDistribution", "init_std": 1.0, "std_type": "scalar"})
    critic = MLPModel(obs, groups, "critic", 1, hidden_dims=[32, 16], obs_normalization=True)
    storage = RolloutStorage("rl", N, T, obs, [A], device)
    return cls(actor, critic, storage, device=device, num_mini_batches=2, num_learning_epochs=3, **kw)


def _train(alg, iterations: int, device: str) -> list[dict]:
    """A synthetic rollout (fixed data stream, the algorithm's own actions) and an update, repeated."""
    data = torch.Generator().manual_seed(1)
    torch.manual_seed(2)
    if device == "cuda":
        torch.cuda.manual_seed(2)
    losses = []
    alg.train_mode()
    for _ in range(iterations):
        with torch.inference_mode():
            obs = _obs(data, device)
            for _ in range(T):
                actions = alg.act(obs)
                obs = _obs(data, device)
                rewards = (-actions.pow(2).sum(-1) + torch.randn(N, generator=data).to(device)).clone()
                dones = (torch.rand(N, generator=data) < 0.2).long().to(device)
                time_outs = (torch.rand(N, generator=data) < 0.1).to(device)
                alg.process_env_step(obs, rewards, dones, {"time_outs": time_outs})
            alg.compute_returns(obs)
        losses.append(alg.update())
    return losses


def _params(alg) -> dict[str, torch.Tensor]:
    out = {f"actor.{k}": v.detach().cpu() for k, v in alg.actor.state_dict().items()}
    out.update({f"critic.{k}": v.detach().cpu() for k, v in alg.critic.state_dict().items()})
    return out


@pytest.mark.parametrize("schedule,desired_kl", [("adaptive", 1e-5), ("adaptive", 10.0), ("adaptive", 0.01),
                                                 ("fixed", 0.01)])
def test_update_matches_rsl_rl(schedule, desired_kl):
    kw = dict(schedule=schedule, desired_kl=desired_kl, learning_rate=1e-3, entropy_coef=0.005)
    ref, ours = _make(PPO, "cpu", **kw), _make(GraphPPO, "cpu", **kw)
    ref_losses, our_losses = _train(ref, 3, "cpu"), _train(ours, 3, "cpu")
    for a, b in zip(ref_losses, our_losses):
        for k in ("value", "surrogate", "entropy"):
            assert b[k] == pytest.approx(a[k], rel=1e-4, abs=1e-6), k
    assert ours.learning_rate == pytest.approx(ref.learning_rate, rel=1e-5)
    if schedule == "adaptive" and desired_kl == 1e-5:
        assert ours.learning_rate < 1e-3 / 1.5**3  # KL far above the target: the rate shrank
    if schedule == "adaptive" and desired_kl == 10.0:
        assert ours.learning_rate > 1e-3 * 1.5**3  # far below: it grew
    pa, pb = _params(ref), _params(ours)
    assert pa.keys() == pb.keys()
    for k in pa:
        torch.testing.assert_close(pb[k], pa[k], rtol=1e-4, atol=1e-5, msg=k)


def test_checkpoint_round_trip_keeps_device_learning_rate():
    a = _make(GraphPPO, "cpu", schedule="adaptive", desired_kl=1e-5)
    _train(a, 2, "cpu")
    state = a.save()
    b = _make(GraphPPO, "cpu", schedule="adaptive", desired_kl=1e-5, learning_rate=5e-4)
    b.load(state, None, strict=True)
    assert b.learning_rate == pytest.approx(a.learning_rate)
    assert b.optimizer.param_groups[0]["lr"] is b._lr  # the KL rule keeps reaching Adam
    before = b.learning_rate
    b.desired_kl = 1e-9  # any step now overshoots: the rate must shrink
    _train(b, 1, "cpu")
    assert b.learning_rate < before
    # A checkpoint of rsl-rl's PPO (a float learning rate) loads too.
    ref = _make(PPO, "cpu", learning_rate=3e-4)
    c = _make(GraphPPO, "cpu")
    c.load(ref.save(), None, strict=True)
    assert c.learning_rate == pytest.approx(3e-4) and c.optimizer.param_groups[0]["lr"] is c._lr


def test_action_std_reads_the_policy_parameters():
    a = _make(GraphPPO, "cpu")
    with torch.no_grad():
        a.actor.distribution.std_param.copy_(torch.tensor([0.5, -1.0, 2.0]))
    torch.testing.assert_close(a.action_std(), torch.tensor([0.5, 1e-6, 2.0]))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_cuda_graph_update_matches_eager():
    kw = dict(schedule="adaptive", desired_kl=0.01, learning_rate=1e-3)
    eager, graphed = _make(GraphPPO, "cuda", **kw), _make(GraphPPO, "cuda", cuda_graphs=True, **kw)
    assert graphed.cuda_graphs and not eager.cuda_graphs
    le, lg = _train(eager, 4, "cuda"), _train(graphed, 4, "cuda")
    assert graphed._update_graphs is not None and graphed._act_graph is not None
    for a, b in zip(le, lg):
        for k in a:
            assert b[k] == pytest.approx(a[k], rel=1e-3, abs=1e-5), k
    assert graphed.learning_rate == pytest.approx(eager.learning_rate, rel=1e-5)
    pa, pb = _params(eager), _params(graphed)
    for k in pa:
        torch.testing.assert_close(pb[k], pa[k], rtol=1e-3, atol=1e-4, msg=k)
