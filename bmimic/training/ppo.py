"""rsl-rl-lib's PPO with a host-sync-free update, optionally replayed from CUDA graphs.

rsl-rl's `PPO.update` reads four scalars back to the host per mini-batch (the KL check of the
adaptive learning rate and three `.item()` loss sums), so the CPU waits for the GPU 80 times per
iteration and cannot queue work ahead; its `act` launches ~40 small kernels per rollout step. At
4096+ envs both are launch-bound, not compute-bound. `GraphPPO` computes the same thing with:

- the learning rate as a device tensor that the KL rule updates in place (`torch.where` instead of
  Python `if`), read by Adam (fused on a GPU) as a tensor;
- the loss sums accumulated on the device and read once per update;
- observation normalisers updated in place (rsl-rl rebinds `_std`, which a captured graph could
  not see);
- with `cuda_graphs` (GPU only): the action sampling captured once, and each mini-batch step
  (forward, KL rule, loss, backward, clipping, Adam) captured once per mini-batch slot, then
  replayed every epoch. The first update runs eagerly as warm-up.
- under torchrun, the mini-batch step's collectives (the KL all-reduce, rank 0's learning-rate
  broadcast, the gradient all-reduce through one fixed flat buffer) are device operations in
  place, so they are captured with the rest of the step. NCCL needs its communicator before a
  capture records a collective: the warm-up update (and the parameter broadcast before it)
  creates it. On CPU ranks (gloo) nothing is captured and the same code runs eagerly.

The mathematics, the order of random draws and the mini-batch order are rsl-rl's
(`tests/training/test_ppo.py` compares the two updates). Not supported: recurrent models, RND, symmetry.
"""

from __future__ import annotations

from contextlib import contextmanager
from itertools import chain
from typing import Any

import torch
import torch.nn as nn
from rsl_rl.algorithms import PPO


class GraphPPO(PPO):
    """rsl-rl's PPO whose update never waits for the GPU; CUDA-graph replay with `cuda_graphs`."""

    optimizer: torch.optim.Optimizer

    def __init__(self, *args, cuda_graphs: bool = False, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        if self.rnd or self.symmetry or self.actor.is_recurrent or self.critic.is_recurrent:
            raise ValueError("GraphPPO supports feed-forward actor and critic without RND or symmetry")
        if type(self.actor.distribution).__name__ != "GaussianDistribution":
            raise ValueError("GraphPPO supports rsl-rl's GaussianDistribution policy")
        if not isinstance(self.optimizer, torch.optim.Adam):
            raise ValueError(f"GraphPPO uses Adam; got {type(self.optimizer).__name__}")
        on_gpu = torch.device(self.device).type == "cuda"
        params = list(chain(self.actor.parameters(), self.critic.parameters()))
        # The lr tensor itself is the param group's lr, so an in-place update reaches Adam.
        self.optimizer = torch.optim.Adam(params, lr=self._lr, fused=on_gpu, capturable=on_gpu,
                                          foreach=False if not on_gpu else None)
        self.optimizer.param_groups[0]["lr"] = self._lr
        self.cuda_graphs = bool(cuda_graphs) and on_gpu
        self._loss_sums = torch.zeros(3, device=self.device)
        self._adv: Any = None  # flat advantages: compute_returns rebinds the storage's tensor each iteration
        self._perm: Any = None
        self._updates_done = 0
        self._update_graphs: list[torch.cuda.CUDAGraph] | None = None
        self._act_graph: tuple | None = None
        self._act_calls = 0
        self._stream: Any = None
        self._grad_flat: torch.Tensor | None = None  # the gradient all-reduce's buffer (torchrun)

    # ------------------------------------------------------------------ learning rate on the device
    @property
    def learning_rate(self) -> float:
        """The current learning rate (a host read: for logging, not for the hot path)."""
        return float(self._lr)

    @learning_rate.setter
    def learning_rate(self, value) -> None:
        if "_lr" not in self.__dict__:  # PPO.__init__ assigns it before the tensor exists
            self._lr = torch.tensor(float(value), dtype=torch.float32, device=self.device)
        else:
            self._lr.fill_(float(value))

    def _adapt_learning_rate(self, old_params, new_params) -> None:
        """rsl-rl's adaptive rule (divide by 1.5 above 2x the KL target, multiply below half),
        as tensor ops. Under torchrun the KL is averaged over the ranks first and rank 0's rate is
        broadcast, as rsl-rl does; both collectives work in place on device tensors, so a CUDA
        graph can hold them."""
        with torch.no_grad():
            kl = self.actor.get_kl_divergence(old_params, new_params).mean()
            if self.is_multi_gpu:
                torch.distributed.all_reduce(kl, op=torch.distributed.ReduceOp.SUM)
                kl = kl / self.gpu_world_size
            lr = self._lr
            lower = torch.clamp(lr / 1.5, min=1e-5)
            higher = torch.clamp(lr * 1.5, max=1e-2)
            shrink = kl > self.desired_kl * 2.0
            grow = (kl < self.desired_kl / 2.0) & (kl > 0.0)
            self._lr.copy_(torch.where(shrink, lower, torch.where(grow, higher, lr)))
            if self.is_multi_gpu:  # rsl-rl's rank 0 decides; a device-side broadcast, no host read
                torch.distributed.broadcast(self._lr, src=0)

    # ------------------------------------------------------------------ acting
    def act(self, obs):
        if not self.cuda_graphs:
            return super().act(obs)
        if self._act_graph is None:
            self._act_calls += 1
            if self._act_calls <= 2:  # warm-up on the capture stream: cuBLAS handles, allocator
                with self._on_capture_stream():
                    return super().act(obs)
            self._act_graph = self._capture_act(obs)
        g, static_obs, actions, values, log_prob, mean, std = self._act_graph
        static_obs.update_(obs)
        g.replay()
        t = self.transition
        t.hidden_states = (None, None)
        t.actions, t.values, t.actions_log_prob = actions, values, log_prob
        t.distribution_params = (mean, std)
        # The stored transition reads this buffer before the next act overwrites it.
        t.observations = static_obs
        return actions

    def _capture_act(self, obs) -> tuple:
        static_obs = obs.clone()
        torch.cuda.synchronize(self.device)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g, stream=self._capture_stream()):
            mean = self._policy_distribution(static_obs)
            std = self.actor.distribution.std
            # torch.normal(mean, std) draws normal_(0, 1) and scales it: the same numbers, without
            # its host-side check that std >= 0, which a capture cannot contain.
            actions = mean + std * torch.randn_like(mean)
            values = self.critic(static_obs)
            log_prob = self.actor.get_output_log_prob(actions)
        return g, static_obs, actions, values, log_prob, mean, std

    def _policy_distribution(self, obs) -> torch.Tensor:
        """The actor's forward pass and Gaussian, without sampling; returns the mean."""
        mean = self.actor(obs)  # a Gaussian's deterministic output is its mean
        self.actor.distribution.update(mean)
        return mean

    def _capture_stream(self) -> torch.cuda.Stream:
        if self._stream is None:
            self._stream = torch.cuda.Stream(self.device)
        return self._stream

    @contextmanager
    def _on_capture_stream(self):
        """Run eager warm-up work on the stream the graphs are captured on, as capture requires."""
        side, main = self._capture_stream(), torch.cuda.current_stream(self.device)
        side.wait_stream(main)
        with torch.cuda.stream(side):
            yield
        main.wait_stream(side)

    # ------------------------------------------------------------------ returns
    def compute_returns(self, obs) -> None:
        super().compute_returns(obs)
        adv = self.storage.advantages.flatten(0, 1)
        if self._adv is None:
            self._adv = torch.empty_like(adv)
        self._adv.copy_(adv)

    # ------------------------------------------------------------------ update
    def _mini_batch_step(self, i: int, mini_batch_size: int, flat: dict) -> None:
        """One rsl-rl mini-batch step on slot i of the permutation; everything stays on the device."""
        idx = self._perm[i * mini_batch_size : (i + 1) * mini_batch_size]
        obs = flat["obs"][idx]
        actions = flat["actions"][idx]
        old_values = flat["values"][idx]
        returns = flat["returns"][idx]
        old_log_prob = flat["log_prob"][idx]
        advantages = self._adv[idx]
        old_params = tuple(p[idx] for p in flat["dist"])
        if self.normalize_advantage_per_mini_batch:
            with torch.no_grad():
                advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        with torch.amp.autocast(device_type=torch.device(self.device).type, enabled=self.use_mixed_precision,
                                dtype=torch.bfloat16):
            mean = self._policy_distribution(obs)
            torch.randn_like(mean)  # rsl-rl draws (and discards) a sample here: keep the RNG stream in step
            log_prob = self.actor.get_output_log_prob(actions)
            values = self.critic(obs)
            new_params = self.actor.output_distribution_params
            entropy = self.actor.output_entropy
            if self.desired_kl is not None and self.schedule == "adaptive":
                self._adapt_learning_rate(old_params, new_params)
            ratio = torch.exp(log_prob - torch.squeeze(old_log_prob))
            adv = torch.squeeze(advantages)
            surrogate_loss = torch.max(-adv * ratio,
                                       -adv * torch.clamp(ratio, 1.0 - self.clip_param, 1.0 + self.clip_param)).mean()
            if self.use_clipped_value_loss:
                value_clipped = old_values + (values - old_values).clamp(-self.clip_param, self.clip_param)
                value_loss = torch.max((values - returns).pow(2), (value_clipped - returns).pow(2)).mean()
            else:
                value_loss = (returns - values).pow(2).mean()
            entropy_mean = entropy.mean()
            loss = surrogate_loss + self.value_loss_coef * value_loss - self.entropy_coef * entropy_mean
        # Gradients stay allocated (zeroed, not freed) so captured graphs keep their addresses.
        self.optimizer.zero_grad(set_to_none=False)
        loss.backward()
        if self.is_multi_gpu:
            self.reduce_parameters()
        nn.utils.clip_grad_norm_(self.actor.parameters(), self.max_grad_norm)
        nn.utils.clip_grad_norm_(self.critic.parameters(), self.max_grad_norm)
        self.optimizer.step()
        with torch.no_grad():
            self._loss_sums += torch.stack((value_loss.detach(), surrogate_loss.detach(), entropy_mean.detach()))

    def update(self) -> dict[str, float]:
        st = self.storage
        batch_size = st.num_envs * st.num_transitions_per_env
        mini_batch_size = batch_size // self.num_mini_batches
        # rsl-rl 5.5 draws one permutation per update and reuses it every epoch.
        perm = torch.randperm(self.num_mini_batches * mini_batch_size, device=self.device)
        if self._perm is None:
            self._perm = perm
        else:
            self._perm.copy_(perm)
        flat = {
            "obs": st.observations.flatten(0, 1),
            "actions": st.actions.flatten(0, 1),
            "values": st.values.flatten(0, 1),
            "returns": st.returns.flatten(0, 1),
            "log_prob": st.actions_log_prob.flatten(0, 1),
            "dist": tuple(p.flatten(0, 1) for p in st.distribution_params),
        }
        self._loss_sums.zero_()
        # Under torchrun the captured steps hold their collectives; every rank captures in the same
        # update (the second), so the ranks' graphs replay matching collectives in the same order.
        capture = self.cuda_graphs
        if capture and self._update_graphs is None and self._updates_done >= 1:
            self._capture_update(mini_batch_size, flat)
        if self._update_graphs is not None:
            for _ in range(self.num_learning_epochs):
                for g in self._update_graphs:
                    g.replay()
        elif capture:
            with self._on_capture_stream():  # the eager warm-up update
                self._epochs(mini_batch_size, flat)
        else:
            self._epochs(mini_batch_size, flat)
        self._updates_done += 1

        obs = flat["obs"]
        for model in (self.actor, self.critic):
            _update_normalization_in_place(model, obs)
        num_updates = self.num_learning_epochs * self.num_mini_batches
        value, surrogate, entropy = (self._loss_sums / num_updates).tolist()  # the update's one host read
        st.clear()
        return {"value": value, "surrogate": surrogate, "entropy": entropy}

    def _epochs(self, mini_batch_size: int, flat: dict) -> None:
        for _ in range(self.num_learning_epochs):
            for i in range(self.num_mini_batches):
                self._mini_batch_step(i, mini_batch_size, flat)

    def _capture_update(self, mini_batch_size: int, flat: dict) -> None:
        """One graph per mini-batch slot; capture records kernels without running them, so the
        update that captures then replays every step like any later update."""
        torch.cuda.synchronize(self.device)
        pool = torch.cuda.graph_pool_handle()
        graphs = []
        for i in range(self.num_mini_batches):
            g = torch.cuda.CUDAGraph()
            with torch.cuda.graph(g, pool=pool, stream=self._capture_stream()):
                self._mini_batch_step(i, mini_batch_size, flat)
            graphs.append(g)
        self._update_graphs = graphs

    def reduce_parameters(self) -> None:
        """rsl-rl's gradient average over the ranks (sum, then divide by the world size), through
        one flat buffer allocated at the first (eager) call: gather the gradients into it,
        all-reduce it in place, scale it, copy it back. No allocation and no host read, so the
        captured mini-batch step holds it; elementwise the same arithmetic as rsl-rl's buckets."""
        grads = [p.grad for p in chain(self.actor.parameters(), self.critic.parameters()) if p.grad is not None]
        numel = sum(g.numel() for g in grads)
        if self._grad_flat is None or self._grad_flat.numel() != numel:
            if len({g.dtype for g in grads}) != 1:
                raise ValueError("GraphPPO's gradient all-reduce needs one dtype for every gradient")
            self._grad_flat = torch.empty(numel, dtype=grads[0].dtype, device=grads[0].device)
        flat = self._grad_flat
        torch.cat([g.reshape(-1) for g in grads], out=flat)
        torch.distributed.all_reduce(flat, op=torch.distributed.ReduceOp.SUM)
        flat.div_(self.gpu_world_size)
        offset = 0
        for g in grads:
            g.copy_(flat[offset : offset + g.numel()].view_as(g))
            offset += g.numel()

    # ------------------------------------------------------------------ state
    def load(self, loaded_dict: dict, load_cfg: dict | None, strict: bool) -> bool:
        self.release_graphs()  # loading replaces the optimiser state the graphs point at
        out = super().load(loaded_dict, load_cfg, strict)
        for group in self.optimizer.param_groups:
            self.learning_rate = float(group["lr"])
            group["lr"] = self._lr
        return out

    def release_graphs(self) -> None:
        """Drop the captured graphs (before destroy_process_group under torchrun, or a reload)."""
        if self._update_graphs is not None or self._act_graph is not None:
            torch.cuda.synchronize(self.device)
        self._update_graphs = None
        self._act_graph = None
        self._act_calls = 0
        self._updates_done = 0

    def action_std(self) -> torch.Tensor:
        """Per-action standard deviation of the Gaussian policy, from its parameters."""
        dist = self.get_policy().distribution
        if dist.std_type == "log":
            return torch.exp(dist.log_std_param.clamp(*dist.log_std_range)).detach()
        return dist.std_param.clamp(*dist.std_range).detach()


def _update_normalization_in_place(model, obs) -> None:
    """rsl-rl's normaliser update, keeping the `_std` buffer's address (captured graphs read it)."""
    if not getattr(model, "obs_normalization", False):
        return
    norm = model.obs_normalizer
    std = norm._std
    model.update_normalization(obs)
    if norm._std is not std:
        std.copy_(norm._std)
        norm._std = std
