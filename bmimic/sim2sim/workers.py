"""Episodes spread over worker processes: one MjData and one single-threaded onnxruntime session per
worker (spawned, so the caller's threads are never forked), each episode optionally perturbed from its
own seeded generator (bmimic.sim2sim.perturb)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple, Sequence

import numpy as np

from bmimic.sim2sim.perturb import Draw
from bmimic.sim2sim.rollout import Episode, Rollout, run_episode
from bmimic.sim2sim.spec import PolicySpec, policy_session

if TYPE_CHECKING:
    from bmimic.motion.motion import Motion
    from bmimic.sim2sim.perturb import Perturbations


class EpisodeTask(NamedTuple):
    """One episode for a worker: where it starts, how long it may run and, when perturbed, its seed."""

    start_frame: int
    horizon_steps: int
    seed: tuple[int, ...] | None = None
    """Entropy of the episode's own numpy generator for the perturbations (None: not perturbed)."""


_WORKER: dict = {}


def _init_worker(policy_path: Path, mjm, spec: PolicySpec, ref: Motion, max_mpkpe_rel_mm: float | None,
                 perturbations: Perturbations | None = None) -> None:
    _WORKER["rollout"] = Rollout(mjm, spec, ref, policy_session(policy_path))
    _WORKER["max_mpkpe_rel_mm"] = max_mpkpe_rel_mm
    _WORKER["perturbations"] = perturbations


def _work(task: EpisodeTask) -> Episode:
    perturbations = _WORKER["perturbations"]
    draw = None
    if perturbations is not None and task.seed is not None:
        draw = Draw(perturbations, np.random.default_rng(list(task.seed)))
    episode = run_episode(_WORKER["rollout"], int(task.start_frame), int(task.horizon_steps),
                          _WORKER["max_mpkpe_rel_mm"], draw=draw)
    if draw is not None:
        episode.row["pushes"] = draw.pushes
    return episode


def run_tasks(policy_path: Path, mjm, spec: PolicySpec, ref: Motion, tasks: Sequence[EpisodeTask], workers: int,
              max_mpkpe_rel_mm: float | None = None,
              perturbations: Perturbations | None = None) -> tuple[list[Episode], float]:
    """(one Episode per task, in order; wall seconds) over `workers` processes (spawned: no fork of the
    caller's threads), each with its own MjData and onnxruntime session. A task with a seed is
    perturbed by `perturbations`, from its own generator, so its draws do not depend on the worker
    that runs it nor on the other tasks."""
    t0 = time.perf_counter()
    workers = max(1, min(workers, len(tasks)))
    init = (policy_path, mjm, spec, ref, max_mpkpe_rel_mm, perturbations)
    if workers == 1:
        _init_worker(*init)
        episodes = [_work(t) for t in tasks]
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker,
                                 initargs=init) as pool:
            episodes = list(pool.map(_work, tasks, chunksize=max(1, len(tasks) // (8 * workers))))
    return episodes, time.perf_counter() - t0


def run_episodes(policy_path: Path, mjm, spec: PolicySpec, ref: Motion, frames: np.ndarray, horizon_steps: int,
                 workers: int, max_mpkpe_rel_mm: float | None = None) -> tuple[list[Episode], float]:
    """(one Episode per start frame, in order; wall seconds): run_tasks with the same horizon for all,
    unperturbed."""
    return run_tasks(policy_path, mjm, spec, ref, [EpisodeTask(int(f), horizon_steps) for f in frames], workers,
                     max_mpkpe_rel_mm)


__all__ = ["EpisodeTask", "run_episodes", "run_tasks"]
