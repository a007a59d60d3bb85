"""Uniform draws U(-half_width, half_width) on the device, for noise and randomisation terms."""

from __future__ import annotations

from typing import Sequence, cast

import torch


class UniformNoise:
    """`noise(shape, half_width)`; list half-widths (one per last-axis entry) are cached on the device
    so that no draw on the step path copies from the host.

    Draws use torch's default generator (seeded by bmimic.runtime.seed_everything), which CUDA-graph
    replay advances (a private generator would have to be registered with every graph)."""

    def __init__(self, device: torch.device | str) -> None:
        self.device = torch.device(device)
        self._half_widths: dict[tuple, torch.Tensor] = {}

    def __call__(self, shape: Sequence[int], half_width: float | Sequence[float]) -> torch.Tensor:
        hw: torch.Tensor | float
        if isinstance(half_width, (list, tuple)):
            key = tuple(float(x) for x in half_width)
            if key not in self._half_widths:
                self._half_widths[key] = torch.tensor(key, dtype=torch.float32, device=self.device)
            hw = self._half_widths[key]
        else:
            hw = float(cast(float, half_width))
        u = torch.rand(shape, device=self.device)
        return (2.0 * u - 1.0) * hw


__all__ = ["UniformNoise"]
