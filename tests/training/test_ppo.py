"""GraphPPO computes rsl-rl's PPO update: same parameters, normalisers, losses and learning rate;
and under torchrun (here 2 CPU ranks, gloo) the same update as one rank given the union of their data."""

from __future__ import annotations

import os

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

from bmimic.training.ppo import GraphPPO
from tests.conftest import RANKS_GROUP, free_port, spawn_ranks

N, T, A = 16, 6, 3  # envs, steps per rollout, actions


def _obs(gen: torch.Generator, device: str, n: int = N) -> TensorDict:
    return TensorDict({"policy": torch.randn(n, 7, generator=gen).to(device),
                       "critic": torch.randn(n, 9, generator=gen).to(device)}, batch_size=[n], device=device)


def _make(cls, device: str, num_envs: int = N, **kw):
    """Models seeded alike (whatever num_envs), rsl-rl storage for num_envs x T transitions."""
    obs = _obs(torch.Generator().manual_seed(0), device, num_envs)
    groups = {"actor": ["policy"], "critic": ["critic"]}
    torch.manual_seed(0)
    actor = MLPModel(obs, groups, "actor", A, hidden_dims=[32, 16], obs_normalization=True,
                     distribution_cfg={"class_name": "GaussianDistribution", "init_std": 1.0, "std_type": "scalar"})
    critic = MLPModel(obs, groups, "critic", 1, hidden_dims=[32, 16], obs_normalization=True)
    storage = RolloutStorage("rl", num_envs, T, obs, [A], device)
    return cls(actor, critic, storage, device=device, num_mini_batches=2, num_learning_epochs=3, **kw)


def _train(alg, iterations: int, device: str, data_seed: int = 1) -> list[dict]:
    """A synthetic rollout (fixed data stream, the algorithm's own actions) and an update, repeated."""
    data = torch.Generator().manual_seed(data_seed)
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


# ----------------------------------------------------------------------------- several ranks, one update
# Rank r's mini-batch k is half of the single rank's mini-batch k. PPO's loss is a mean over the
# mini-batch, so the ranks' averaged gradients are exactly the single rank's gradient, and their
# averaged KL the single rank's KL; clipping, Adam and the normalisers (which rsl-rl all-reduces)
# then agree too. What differs is only the order of floating-point sums.
WORLD, E_RANK, UPDATES, M = 2, 8, 2, 2  # ranks, envs per rank, updates, mini-batches (as _make)
B = E_RANK * T  # transitions per rank and update; the single rank has WORLD * B
SEED_ONE, SEED_RANK = 1000, 2000
SCHEDULES = {"adaptive": dict(schedule="adaptive", desired_kl=0.01, learning_rate=1e-3, entropy_coef=0.005),
             "fixed": dict(schedule="fixed", learning_rate=1e-3, entropy_coef=0.005)}
KEYS = ("policy", "critic", "actions", "values", "returns", "advantages", "log_prob", "mean", "std")


def _perm(n: int, seed: int) -> torch.Tensor:
    """The permutation an update draws first, after torch.manual_seed(seed)."""
    return torch.randperm(n, generator=torch.Generator().manual_seed(seed))


def _split_batches() -> dict:
    """UPDATES batches for one rank (WORLD * B rows each) and each rank's share, placed so that
    under its own permutation rank r's mini-batch k holds half r of the single rank's mini-batch k."""
    gen = torch.Generator().manual_seed(5)
    frozen = _make(GraphPPO, "cpu").actor  # the initial policy, the same in every process
    h = B // M
    one, ranks = [], [[] for _ in range(WORLD)]
    for u in range(UPDATES):
        p_one = _perm(WORLD * B, SEED_ONE + u)
        owner = torch.empty(WORLD * B, dtype=torch.long)
        owner[p_one.view(M, WORLD, h)] = torch.arange(WORLD).view(1, WORLD, 1)
        obs = _obs(gen, "cpu", WORLD * B)
        with torch.no_grad():
            frozen.distribution.update(frozen(obs))
            mean, std = (x.clone() for x in frozen.output_distribution_params)
        # Rank 1's rows were acted on by a policy one std away, rank 0's by the current one: alone,
        # rank 0's KL is near zero (the adaptive rate would grow), the union's is far above
        # desired_kl (it shrinks), so rsl-rl's KL all-reduce decides the learning rate.
        mean = mean + (owner == 1).unsqueeze(-1) * std
        actions = mean + std * torch.randn(mean.shape, generator=gen)
        log_prob = torch.distributions.Normal(mean, std).log_prob(actions).sum(-1, keepdim=True)
        values = torch.randn(WORLD * B, 1, generator=gen)
        rows = {"policy": obs["policy"], "critic": obs["critic"], "actions": actions, "values": values,
                "returns": values + torch.randn(WORLD * B, 1, generator=gen),
                "advantages": torch.randn(WORLD * B, 1, generator=gen), "log_prob": log_prob, "mean": mean, "std": std}
        one.append(rows)
        for r in range(WORLD):
            where = torch.empty(B, dtype=torch.long)
            where[_perm(B, SEED_RANK + 10 * u + r)] = p_one.view(M, WORLD, h)[:, r].reshape(-1)
            ranks[r].append({k: v[where] for k, v in rows.items()})
    return {"one": one, "ranks": ranks}


def _fill(alg, rows: dict) -> None:
    """Write a batch into the rollout storage, as a rollout and compute_returns would have left it."""
    st = alg.storage
    flat = {"policy": st.observations["policy"], "critic": st.observations["critic"], "actions": st.actions,
            "values": st.values, "returns": st.returns, "advantages": st.advantages, "log_prob": st.actions_log_prob}
    for k, dst in flat.items():
        dst.flatten(0, 1).copy_(rows[k])
    shape = st.actions.shape
    st.distribution_params = (rows["mean"].reshape(shape).clone(), rows["std"].reshape(shape).clone())
    if isinstance(alg, GraphPPO):  # what its compute_returns keeps (which would normalise per rank)
        alg._adv = st.advantages.flatten(0, 1).clone()


def _updates(alg, batches: list[dict], seeds: list[int]) -> dict:
    alg.train_mode()
    losses = []
    for rows, seed in zip(batches, seeds):
        _fill(alg, rows)
        torch.manual_seed(seed)
        losses.append(alg.update())
        if isinstance(alg, GraphPPO):  # the permutation _split_batches planned for
            assert torch.equal(alg._perm, _perm(len(alg._perm), seed))
    return {"params": _params(alg), "lr": float(alg.learning_rate), "losses": losses}


def _rank_updates(rank: int, folder: str) -> None:
    batches = torch.load(os.path.join(folder, "batches.pt"), weights_only=True)["ranks"][rank]
    seeds = [SEED_RANK + 10 * u + rank for u in range(UPDATES)]
    multi = {"global_rank": rank, "local_rank": rank, "world_size": WORLD}
    out = {}
    for name, kw in SCHEDULES.items():
        for variant, cls in (("graph", GraphPPO), ("rsl_rl", PPO), ("no_grad_all_reduce", GraphPPO)):
            alg = _make(cls, "cpu", num_envs=E_RANK, multi_gpu_cfg=multi, **kw)
            if variant == "no_grad_all_reduce":  # the negative control: each rank steps alone
                alg.reduce_parameters = lambda: None
            out[f"{name}/{variant}"] = _updates(alg, batches, seeds)
    torch.save(out, os.path.join(folder, f"rank{rank}.pt"))


@pytest.fixture(scope="module")
def ranks_and_one(tmp_path_factory):
    """Each rank's results (2 gloo ranks) and the single rank's on the union of their data."""
    folder = tmp_path_factory.mktemp("ranks")
    batches = _split_batches()
    torch.save(batches, folder / "batches.pt")
    spawn_ranks(_rank_updates, (str(folder),), WORLD, folder)
    ranks = [torch.load(folder / f"rank{r}.pt", weights_only=True) for r in range(WORLD)]
    one = {name: _updates(_make(GraphPPO, "cpu", num_envs=WORLD * E_RANK, **kw), batches["one"],
                          [SEED_ONE + u for u in range(UPDATES)]) for name, kw in SCHEDULES.items()}
    return ranks, one


def _assert_params_close(got: dict, want: dict) -> None:
    assert got.keys() == want.keys()
    for k in want:
        torch.testing.assert_close(got[k], want[k], rtol=1e-4, atol=1e-5, msg=k)


@pytest.mark.slow  # two spawned CPU ranks
@RANKS_GROUP
@pytest.mark.parametrize("schedule", list(SCHEDULES))
def test_two_ranks_update_as_one_rank_with_the_union_of_their_data(ranks_and_one, schedule):
    ranks, one = ranks_and_one
    r0, r1 = (r[f"{schedule}/graph"] for r in ranks)
    ref = one[schedule]
    # The ranks hold one policy, bit for bit (normalisers included), and one learning rate.
    assert r0["lr"] == r1["lr"]
    for k in r0["params"]:
        assert torch.equal(r0["params"][k], r1["params"][k]), k
    # ... the single rank's on the union, to test_update_matches_rsl_rl's tolerance.
    _assert_params_close(r0["params"], ref["params"])
    assert r0["lr"] == pytest.approx(ref["lr"], rel=1e-5)
    if schedule == "adaptive":
        assert ref["lr"] < 1e-3 / 1.5**5  # the union's KL shrank the rate (rank 0's own would grow it)
    # Each rank reports its own mini-batches' losses; their mean is the union's.
    for u in range(UPDATES):
        for k in ("value", "surrogate", "entropy"):
            mean = sum(r[f"{schedule}/graph"]["losses"][u][k] for r in ranks) / WORLD
            assert mean == pytest.approx(ref["losses"][u][k], rel=1e-4, abs=1e-6), (u, k)
    # ... and rsl-rl's own multi-GPU PPO on the same ranks.
    for r in ranks:
        _assert_params_close(r[f"{schedule}/graph"]["params"], r[f"{schedule}/rsl_rl"]["params"])
        assert r[f"{schedule}/graph"]["lr"] == pytest.approx(r[f"{schedule}/rsl_rl"]["lr"], rel=1e-5)
    # Without the gradient all-reduce the same comparison fails.
    alone = ranks[0][f"{schedule}/no_grad_all_reduce"]["params"]
    assert not all(torch.allclose(alone[k], ref["params"][k], rtol=1e-4, atol=1e-5) for k in ref["params"])


def _rank_graphs(rank: int, port: int, folder: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.cuda.set_device(rank)
    dist.init_process_group("nccl", rank=rank, world_size=WORLD)
    try:
        multi = {"global_rank": rank, "local_rank": rank, "world_size": WORLD}
        out = {}
        for name, graphs in (("eager", False), ("graphed", True)):
            alg = _make(GraphPPO, "cuda", cuda_graphs=graphs, multi_gpu_cfg=multi, schedule="adaptive",
                        desired_kl=0.01, learning_rate=1e-3)
            alg.broadcast_parameters()  # as Trainer.learn starts; it also creates the NCCL communicator
            losses = _train(alg, 4, "cuda", data_seed=1 + rank)  # each rank its own data
            out[name] = {"params": _params(alg), "lr": float(alg.learning_rate), "losses": losses,
                         "captured": alg._update_graphs is not None}
            alg.release_graphs()  # before destroy_process_group (pytorch/pytorch#115388)
        torch.save(out, os.path.join(folder, f"rank{rank}.pt"))
    finally:
        dist.destroy_process_group()


@pytest.mark.skipif(not torch.cuda.is_available() or torch.cuda.device_count() < WORLD,
                    reason="the NCCL collectives captured in the update need 2 GPUs")
def test_cuda_graph_update_under_torchrun_matches_eager(tmp_path):
    """2 GPUs (NCCL): the captured update, its collectives inside the graphs, against the eager one."""
    mp.spawn(_rank_graphs, args=(free_port(), str(tmp_path)), nprocs=WORLD, join=True)
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(WORLD)]
    for name in ("eager", "graphed"):  # one policy on both ranks, though their data differ
        a, b = (r[name] for r in ranks)
        assert a["lr"] == b["lr"]
        for k in a["params"]:
            assert torch.equal(a["params"][k], b["params"][k]), (name, k)
    for r in ranks:
        eager, graphed = r["eager"], r["graphed"]
        assert graphed["captured"] and not eager["captured"]
        for le, lg in zip(eager["losses"], graphed["losses"]):
            for k in le:
                assert lg[k] == pytest.approx(le[k], rel=1e-3, abs=1e-5), k
        assert graphed["lr"] == pytest.approx(eager["lr"], rel=1e-5)
        for k in eager["params"]:
            torch.testing.assert_close(graphed["params"][k], eager["params"][k], rtol=1e-3, atol=1e-4, msg=k)
