"""GraphPPO's device operations that keep their buffers' addresses and never read back to the host, so a
captured CUDA graph can hold them: the gradient all-reduce through one flat buffer and the normaliser update."""

from __future__ import annotations

import torch


def average_gradients(grads: list[torch.Tensor], flat: torch.Tensor | None, world_size: int) -> torch.Tensor:
    """rsl-rl's gradient average over the ranks (sum, then divide by the world size), through one flat
    buffer (`flat`, allocated here at the first, eager call and returned for the next): gather the
    gradients into it, all-reduce it in place, scale it, copy it back. No allocation and no host read
    after the first call; elementwise the same arithmetic as rsl-rl's buckets."""
    numel = sum(g.numel() for g in grads)
    if flat is None or flat.numel() != numel:
        if len({g.dtype for g in grads}) != 1:
            raise ValueError("GraphPPO's gradient all-reduce needs one dtype for every gradient")
        flat = torch.empty(numel, dtype=grads[0].dtype, device=grads[0].device)
    torch.cat([g.reshape(-1) for g in grads], out=flat)
    torch.distributed.all_reduce(flat, op=torch.distributed.ReduceOp.SUM)
    flat.div_(world_size)
    offset = 0
    for g in grads:
        g.copy_(flat[offset : offset + g.numel()].view_as(g))
        offset += g.numel()
    return flat


def update_normalization_in_place(model, obs) -> None:
    """rsl-rl's normaliser update, keeping the `_std` buffer's address (captured graphs read it)."""
    if not getattr(model, "obs_normalization", False):
        return
    norm = model.obs_normalizer
    std = norm._std
    model.update_normalization(obs)
    if norm._std is not std:
        std.copy_(norm._std)
        norm._std = std
