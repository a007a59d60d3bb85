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

With `overlap_update` (bmimic.training.overlap) each update runs on the graphs' side stream while the
next rollout collects, acting with the policy from before that update. Everything that reads the learner
(get_policy, save, load) waits for the update in flight first; the losses and learning rate an update
returns are the latest finished update's (one iteration late on a GPU). On a CPU the update runs in
line with the same lag. One process only.
"""

from __future__ import annotations

import math
from contextlib import contextmanager, nullcontext
from itertools import chain
from typing import Any

import torch
import torch.nn as nn
from rsl_rl.algorithms import PPO

from bmimic.training.inplace import average_gradients, update_normalization_in_place
from bmimic.training.overlap import Behaviour, StagedRollout


class GraphPPO(PPO):
    """rsl-rl's PPO whose update never waits for the GPU; CUDA-graph replay with `cuda_graphs`."""

    optimizer: torch.optim.Optimizer

    def __init__(self, *args, cuda_graphs: bool = False, overlap_update: bool = False, **kwargs) -> None:
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
        self.overlap_update = bool(overlap_update)
        if self.overlap_update and self.is_multi_gpu:  # two streams' collectives on one communicator would race
            raise ValueError("GraphPPO's overlap_update runs on one process")
        self._act_noise: torch.Tensor | None = None  # overlap_update with graphs: the actions' noise, drawn eagerly
        self._behaviour = Behaviour(self.actor, self.critic) if self.overlap_update else None
        self._staged = StagedRollout()  # overlap_update: the rollout copy the update in flight reads
        self._in_flight = False  # an update was launched and not waited for
        self._finished = {"value": math.nan, "surrogate": math.nan, "entropy": math.nan}
        self._lr_seen = float(self._lr)  # the learning rate after the latest finished update (host)

    # ------------------------------------------------------------------ learning rate on the device
    @property
    def learning_rate(self) -> float:
        """The current learning rate (a host read: for logging, not for the hot path). With
        overlap_update: the rate after the latest finished update, read when it was waited for."""
        if getattr(self, "overlap_update", False):
            return self._lr_seen
        return float(self._lr)

    @learning_rate.setter
    def learning_rate(self, value) -> None:
        if "_lr" not in self.__dict__:  # PPO.__init__ assigns it before the tensor exists
            self._lr = torch.tensor(float(value), dtype=torch.float32, device=self.device)
        else:
            self._lr.fill_(float(value))
        self._lr_seen = float(value)

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
        with self._acting():  # overlap_update: the behaviour policy acts
            return self._act(obs)

    def _act(self, obs):
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
        if self._act_noise is not None:
            self._act_noise.normal_()  # eager, on this stream: see _capture_act
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
        if self.overlap_update:
            self._act_noise = torch.empty_like(self.storage.actions[0])  # [num_envs, num_actions]
        torch.cuda.synchronize(self.device)
        g = torch.cuda.CUDAGraph()
        with torch.cuda.graph(g, stream=self._capture_stream()):
            mean = self._policy_distribution(static_obs)
            std = self.actor.distribution.std
            # torch.normal(mean, std) draws normal_(0, 1) and scales it: the same numbers, without
            # its host-side check that std >= 0, which a capture cannot contain.
            # overlap_update: a graph's draw reads an offset that any graph's replay rewrites on its own stream
            # (the update's, on the side stream), so the noise is drawn eagerly before each replay instead.
            noise = self._act_noise if self.overlap_update else torch.randn_like(mean)
            actions = mean + std * noise
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

    def _acting(self):
        return self._behaviour.acting(self) if self._behaviour is not None else nullcontext()

    # ------------------------------------------------------------------ returns
    def compute_returns(self, obs) -> None:
        with self._acting():  # the bootstrap value comes from the critic that valued the rollout
            super().compute_returns(obs)
        if self.overlap_update:
            return  # staged by the update, once the update in flight is done reading them
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
            if not self.overlap_update:  # (overlapped, the update's graphs must draw nothing: _capture_act)
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
        if self.overlap_update:
            return self._overlapped_update()
        self._launch_update(self._flat_storage())
        self.storage.clear()
        return self._read_losses()

    def _flat_storage(self) -> dict:
        st = self.storage
        return {
            "obs": st.observations.flatten(0, 1),
            "actions": st.actions.flatten(0, 1),
            "values": st.values.flatten(0, 1),
            "returns": st.returns.flatten(0, 1),
            "log_prob": st.actions_log_prob.flatten(0, 1),
            "dist": tuple(p.flatten(0, 1) for p in st.distribution_params),
        }

    def _read_losses(self) -> dict[str, float]:
        """The finished update's mean losses and learning rate: the update's one host read."""
        num_updates = self.num_learning_epochs * self.num_mini_batches
        value, surrogate, entropy, lr = torch.cat((self._loss_sums / num_updates, self._lr.view(1))).tolist()
        self._lr_seen = lr
        self._finished = {"value": value, "surrogate": surrogate, "entropy": entropy}
        return dict(self._finished)

    def _overlapped_update(self) -> dict[str, float]:
        """Wait for the update in flight, hand its result to the behaviour policy, stage this rollout and
        launch its update on the side stream (in line on a CPU, and for the eager warm-up update)."""
        self.wait_update()
        assert self._behaviour is not None
        self._behaviour.copy_from(self._raw_actor, self._raw_critic)
        flat, self._adv = self._staged.stage(self._flat_storage(), self.storage.advantages.flatten(0, 1))
        if self.cuda_graphs and self._updates_done >= 1:  # graphs captured (now or before): on the side stream
            side = self._capture_stream()
            side.wait_stream(torch.cuda.current_stream(self.device))  # the staged copy is ready
            with torch.cuda.stream(side):
                self._launch_update(flat)
            self._in_flight = True
        else:
            self._launch_update(flat)
            self._read_losses()
        self.storage.clear()
        return dict(self._finished)

    def wait_update(self) -> None:
        """The current stream waits for the update in flight (if any), then its losses are read."""
        if not self._in_flight:
            return
        torch.cuda.current_stream(self.device).wait_stream(self._capture_stream())
        self._in_flight = False
        self._read_losses()

    def _launch_update(self, flat: dict) -> None:
        """Queue one update over `flat` on the current stream (its losses accumulate in _loss_sums)."""
        batch_size = flat["obs"].shape[0]
        mini_batch_size = batch_size // self.num_mini_batches
        # rsl-rl 5.5 draws one permutation per update and reuses it every epoch.
        perm = torch.randperm(self.num_mini_batches * mini_batch_size, device=self.device)
        if self._perm is None:
            self._perm = perm
        else:
            self._perm.copy_(perm)
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
            update_normalization_in_place(model, obs)

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
        """rsl-rl's gradient average over the ranks, capturable (bmimic.training.inplace)."""
        grads = [p.grad for p in chain(self.actor.parameters(), self.critic.parameters()) if p.grad is not None]
        self._grad_flat = average_gradients(grads, self._grad_flat, self.gpu_world_size)

    # ------------------------------------------------------------------ state
    def get_policy(self):
        self.wait_update()  # the learner's weights, not those an update in flight is writing
        return super().get_policy()

    def compile(self, mode: str | None = None) -> None:
        super().compile(mode)
        behaviour: Behaviour | None = getattr(self, "_behaviour", None)  # (None while PPO.__init__ runs)
        if behaviour is not None:
            behaviour.compile(mode)

    def save(self) -> dict:
        self.wait_update()
        state = super().save()
        if self._behaviour is not None:  # the policy the next rollout acts with: a resume continues the lag
            state.update(self._behaviour.state_dict())
        return state

    def load(self, loaded_dict: dict, load_cfg: dict | None, strict: bool) -> bool:
        self.release_graphs()  # loading replaces the optimiser state the graphs point at
        out = super().load(loaded_dict, load_cfg, strict)
        for group in self.optimizer.param_groups:
            self.learning_rate = float(group["lr"])
            group["lr"] = self._lr
        if self._behaviour is not None:
            self._behaviour.load(loaded_dict, strict, self._raw_actor, self._raw_critic)
        return out

    def release_graphs(self) -> None:
        """Drop the captured graphs (before destroy_process_group under torchrun, or a reload)."""
        self.wait_update()
        if self._update_graphs is not None or self._act_graph is not None:
            torch.cuda.synchronize(self.device)
        self._update_graphs = None
        self._act_graph = None
        self._act_calls = 0
        self._updates_done = 0

    def action_std(self) -> torch.Tensor:
        """Per-action standard deviation of the Gaussian policy, from its parameters."""
        # With overlap_update, the policy that acted (reading the learner would wait for the update).
        dist = (self._behaviour.modules[0] if self._behaviour is not None else self.get_policy()).distribution
        if dist.std_type == "log":
            return torch.exp(dist.log_std_param.clamp(*dist.log_std_range)).detach()
        return dist.std_param.clamp(*dist.std_range).detach()
