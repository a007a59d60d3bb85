"""Where a run's numbers go besides its tables: TensorBoard or W&B scalars, the progress bar on a
terminal (else a console line every `line_every` iterations, so that SLURM logs and train.log get
lines, not carriage-return frames) and the warnings about broken worlds.

The Trainer's loop calls one `RunLogger`; the back-end is opened on the first write (`open`), so a
launch refused before training writes nothing. Under torchrun only rank 0 logs (`enabled`); the
warnings come from every rank.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from pathlib import Path
from typing import Any

from bmimic.cli.extras import require_extra
from bmimic.runs.folder import TENSORBOARD_DIR
from bmimic.runs.schema import FAILURE_RATE

log = logging.getLogger(__name__)

LOGGERS = ("tensorboard", "wandb", "none")
"""Values of the `logger` config key."""

_TAGS = {
    "mean_episode_length": "Train/mean_episode_length", "mean_reward": "Train/mean_reward",
    FAILURE_RATE: "Train/failure_rate", "episodes": "Train/episodes",
    "sampling_entropy": "Sampler/entropy", "top1_prob": "Sampler/top1_prob", "top1_bin": "Sampler/top1_bin",
    "fps": "Perf/total_fps", "collection_time_s": "Perf/collection_time", "learning_time_s": "Perf/learning_time",
    "learning_rate": "Loss/learning_rate", "action_std": "Policy/mean_std",
    "nonfinite_resets": "Sim/nonfinite_resets", "out_of_bounds_resets": "Sim/out_of_bounds_resets",
    "overflow_worlds": "Sim/overflow_worlds",
}
"""Scalar tag of each train_metrics column (rsl-rl's names where it has one)."""
TAG_GROUPS = {"loss": "Loss", "reward": "Episode_Reward", "termination": "Episode_Termination", "metrics": "Metrics"}
"""TensorBoard tag group of each `<group>/<name>` column group of train_metrics (the env logs reward/,
termination/ and metrics/ per term; the runner copies those groups into the row)."""


LINES_PER_RUN = 50
"""Without a progress bar, about this many console lines per run at most."""


def line_every(iterations: int) -> int:
    """Iterations between console lines: the smallest of 1, 2, 5, 10, 20, 50, ... giving at most
    LINES_PER_RUN lines for `iterations`."""
    step = 1
    while iterations > LINES_PER_RUN * step:
        step = step * 5 // 2 if str(step).startswith("2") else step * 2
    return step


class RunLogger:
    """TensorBoard / W&B scalars, the console and the progress bar of one training run."""

    def __init__(self, backend: str, run_dir: str | os.PathLike, run_name: str, wandb_project: str = "bmimic",
                 progress_bar: bool = True, enabled: bool = True) -> None:
        if backend == "wandb":  # fail at start-up, not at the first logged scalar
            require_extra("wandb", "logger=wandb")
        self.backend = backend if enabled else "none"
        self.run_dir = Path(run_dir)
        self.run_name = run_name
        self.wandb_project = wandb_project
        self.progress_bar = progress_bar and enabled and sys.stderr.isatty()  # tqdm redraws a terminal line
        self._line_every, self._end_it = 10, 0
        self._paced, self._start_it = True, 0  # start() arms the pace line
        self.enabled = enabled
        self.writer: Any = None
        self._opened = False
        self._bar = None

    def open(self) -> None:
        """Open the TensorBoard / W&B writer (idempotent); the first write into the run folder."""
        if self._opened:
            return
        self._opened = True
        if self.backend == "wandb":
            import wandb

            self.writer = _WandbWriter(wandb.init(project=self.wandb_project, name=self.run_name,
                                                  dir=str(self.run_dir)))
        elif self.backend == "tensorboard":
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(self.run_dir / TENSORBOARD_DIR), flush_secs=30)

    def start(self, start_it: int, end_it: int) -> None:
        """The training loop begins (a progress bar from `start_it` to `end_it`)."""
        self.open()
        self._line_every, self._end_it = line_every(end_it - start_it), end_it
        self._paced = end_it - start_it < 3  # a pace line needs a steady iteration and one after it
        self._start_it = start_it
        if self.progress_bar and end_it > start_it:
            from tqdm import tqdm

            self._bar = tqdm(total=end_it, initial=start_it, desc="train", unit="it", dynamic_ncols=True)

    def iteration(self, it: int, row: dict, broken_so_far: int, sampler=None, layout=None) -> None:
        """One train_metrics row: its scalars, the sampler's distribution over time when `sampler` and
        its bin `layout` are given (a histogram over the bins' time edges), the progress bar or every
        10th a console line, and the warnings about broken worlds (`broken_so_far`: world-steps reset
        so far in the run)."""
        broken = row["nonfinite_resets"] + row["out_of_bounds_resets"]
        if broken > 0:
            log.warning("iteration %d: reset %d broken world-steps (%d non-finite, %d beyond sim.max_abs_qvel / "
                        "sim.max_root_distance_m / env.max_abs_step_reward); %d so far", it, int(broken),
                        int(row["nonfinite_resets"]), int(row["out_of_bounds_resets"]), broken_so_far)
        if row["overflow_worlds"] > 0:
            log.warning("iteration %d: %d world-steps overflowed the contact/constraint buffers; raise "
                        "sim.nconmax / sim.njmax", it, int(row["overflow_worlds"]))
        if self.writer is not None:
            self._scalars(it, row)
            if sampler is not None and hasattr(self.writer, "add_histogram_raw"):
                self._histogram(it, sampler.probabilities().detach().cpu().double().numpy(),
                                layout.edges_s.cpu().numpy())
        if self._bar is not None:
            self._bar.update(1)
            self._bar.set_postfix(ep_len=f"{row['mean_episode_length']:.0f}", reward=f"{row['mean_reward']:.2f}",
                                  fps=f"{row['fps']:.0f}", **({"broken_worlds": int(broken_so_far)}
                                                              if broken_so_far else {}))
            return  # (the bar shows its own pace and ETA)
        if not self.enabled:
            return
        if not self._paced and it == self._start_it + 1:
            self._paced = True
            iteration_s = row.get("collection_time_s", math.nan) + row.get("learning_time_s", math.nan)
            if math.isfinite(iteration_s):
                log.info(pace_line(iteration_s, self._end_it - it - 1))
        if (it + 1) % self._line_every == 0 or it + 1 == self._end_it:
            log.info("iteration %d/%d: episode length %.1f, reward %.3f, failure rate %.3f, lr %.1e, %.0f steps/s",
                     it + 1, self._end_it, row["mean_episode_length"], row["mean_reward"], row[FAILURE_RATE],
                     row["learning_rate"], row["fps"])

    def evaluation(self, iteration: int, summary: dict) -> None:
        """One evaluation's summary (bmimic.training.evaluator.summarize)."""
        self.open()
        if self.writer is not None:
            for k, v in summary.items():
                self.writer.add_scalar(f"Eval/{k}", v, iteration)
        log.info("eval at iteration %d: failure rate %.3f, bins mastered %.2f, MPKPE %.1f mm", iteration,
                 summary["eval_failure_rate"], summary["eval_bins_mastered_frac"], summary["eval_mpkpe_mm"])

    def whole_clip(self, iteration: int, summary: dict) -> None:
        """One whole-clip evaluation's summary (bmimic.training.whole_clip), as `Eval/whole_clip_*` scalars."""
        self.open()
        if self.writer is not None:
            for k, v in summary.items():
                self.writer.add_scalar(f"Eval/{k}", v, iteration)

    def end(self) -> None:
        """The training loop ended (the bar closes; the writer stays open for the final evaluation)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def close(self) -> None:
        """End the loop's output and close the back-end."""
        self.end()
        if self.writer is not None:
            self.writer.close()

    def _scalars(self, it: int, row: dict) -> None:
        for k, v in row.items():
            if isinstance(v, float) and math.isnan(v):
                continue
            tag = _TAGS.get(k)
            if tag is None and "/" in k:
                prefix, name = k.split("/", 1)
                tag = TAG_GROUPS[prefix] + "/" + name
            if tag is not None:
                self.writer.add_scalar(tag, v, it)

    def _histogram(self, it: int, probs, edges) -> None:
        self.writer.add_histogram_raw(
            "Sampler/probability_over_time_s", min=float(edges[0]), max=float(edges[-1]), num=len(probs),
            sum=float((probs * edges[:-1]).sum()), sum_squares=float((probs * edges[:-1] ** 2).sum()),
            bucket_limits=edges[1:].tolist(), bucket_counts=probs.tolist(), global_step=it,
        )


class _WandbWriter:
    """The subset of SummaryWriter the logger uses, over a W&B run (offline with WANDB_MODE=offline)."""

    def __init__(self, run) -> None:
        self.run = run

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.run.log({tag: value}, step=step)

    def close(self) -> None:
        """Finish the W&B run."""
        self.run.finish()


def pace_line(iteration_s: float, left: int) -> str:
    """The estimate a run gives once its second iteration is timed (its first may hold one-time work:
    torch's first calls, graph capture): the iterations `left` at that pace, training alone."""
    total = iteration_s * left
    when = f"{total / 3600:.1f} h" if total >= 5400 else f"{total / 60:.0f} min" if total >= 90 else f"{total:.0f} s"
    return (f"pace: {iteration_s:.2f} s per iteration; the {left} iterations left take about {when} of training "
            "(evaluations come on top)")


def done_line(metrics: dict, wall_key: str, run_dir, broken: int, overflow: int) -> str:
    """A run's closing line: its iterations, training's seconds (over every launch of a resumed run) and this
    whole command's, the final failure rate, the world-steps reset or overflowed."""
    from bmimic.cli.startup import command_wall_s

    return (f"done: {metrics['iterations']} iterations, {metrics[wall_key]:.0f} s of training in all (a resumed run's "
            f"launches together; {command_wall_s():.0f} s this whole command), eval failure rate "
            f"{metrics['final_eval_failure_rate']:.3f}"
            + (f"; {broken} broken world-steps were reset" if broken else "")
            + (f"; {overflow} world-steps overflowed the contact/constraint buffers (raise sim.nconmax / sim.njmax)"
               if overflow else "") + f" -> {run_dir}")


def final_evaluation_line(windows: bool, robust: bool, whole_clips: bool) -> str:
    """What a run evaluates after its last iteration, said before it starts."""
    kinds = [name for name, on in (("the windows", windows), ("the windows under pushes and noise", robust),
                                   ("the whole clips", whole_clips)) if on]
    return "final evaluation: " + (", then ".join(kinds) if kinds else "none due (the last iteration's stands)")
