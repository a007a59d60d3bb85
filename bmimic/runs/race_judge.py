"""A race's whole-clip finish line judged in native MuJoCo beside training (`bmimic.race --native-whole-clip W`).

A MuJoCo-Warp whole-clip evaluation stops training for 51-79 s on an H200 (latency-bound: the 131.5 s dance is
6575 sequential control steps), so the race's 10% evaluation share left no room for one in a 1250 s race
(docs/benchmarks.md, 2026-11-29). The exported policy in native MuJoCo runs on CPU cores instead (1.6 s per
131.5 s rollout on one core, measured), while the GPU trains on. `NativeJudge` keeps one
`python -m bmimic.sim2sim motion_policy_<it>.onnx --whole-clip R --conditions robust` running at a time, on the
newest checkpoint not yet judged, from the first window evaluation at `after_success` on, and hands back each
result with its checkpoint's iteration. The race times a threshold at that checkpoint's evaluation (the
policy's time); the result itself arrives one or more evaluations later, and the race stops then. Light: no
torch, no sim2sim import (the evaluation is a child process), so bmimic.race may hold it on rank 0.
"""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path
from typing import Callable

from bmimic.runs import safe_read
from bmimic.runs.folder import (
    EVAL_SUMMARY,
    MOTION_POLICY,
    SIM2SIM_DIR,
    SIM2SIM_WHOLE_CLIP,
    checkpoint_label,
    checkpoints_dir,
    motion_policy_onnx_name,
)
from bmimic.runs.schema import whole_clip_success

log = logging.getLogger(__name__)

NATIVE_MODEL = "bmimic_g1"
"""The robot model sim2sim judges on (its default --model: the run's own robot config), and its folder name."""
JUDGE_LOG = "race_native_judge.log"
"""The judge's children's output, in RUN/sim2sim/."""


def native_summary_path(run_dir: str | Path, iteration: int) -> Path:
    """Where sim2sim's whole-clip summary of checkpoint `iteration` lands (analysis.race_whole_clip --native reads it)."""
    return Path(run_dir) / SIM2SIM_DIR / NATIVE_MODEL / checkpoint_label(iteration) / SIM2SIM_WHOLE_CLIP / EVAL_SUMMARY


def robust_success(path: Path) -> float | None:
    """The robust whole-clip success in a sim2sim summary (None: absent, unreadable or not a fraction)."""
    try:
        return whole_clip_success(safe_read.read_json(path), "robust")
    except (OSError, ValueError):
        return None


class NativeJudge:
    """One native whole-clip evaluation at a time of a run's newest checkpoint (module docstring)."""

    def __init__(self, workers: int, rollouts: int = 128, seed: int = 0, after_success: float = 0.95,
                 command: Callable[[Path, Path], list[str]] | None = None) -> None:
        self.workers, self.rollouts, self.seed, self.after_success = workers, rollouts, seed, after_success
        self.command = command or self.sim2sim_command
        """(ONNX, out folder) -> the child's argv (tests plant a stand-in)."""
        self.opened = False
        """The windows have reached `after_success` (then for good)."""
        self.started: list[int] = []
        """Iterations whose evaluation was started, in order."""
        self.running: tuple[int, subprocess.Popen] | None = None

    def sim2sim_command(self, onnx: Path, out: Path) -> list[str]:
        return [sys.executable, "-m", "bmimic.sim2sim", str(onnx), "--whole-clip", str(self.rollouts), "--conditions",
                "robust", "--workers", str(self.workers), "--seed", str(self.seed), "--out", str(out)]

    def _newest(self, run_dir: Path) -> tuple[int, Path] | None:
        """The newest exported checkpoint after the last one started (None: none yet)."""
        last = self.started[-1] if self.started else -1
        found = [(int(m.group(1)), p) for p in checkpoints_dir(run_dir).glob("*.onnx")
                 if (m := MOTION_POLICY.search(p.name)) and int(m.group(1)) > last]
        return max(found) if found else None

    def _collect(self, run_dir: Path) -> list[tuple[int, float]]:
        if self.running is None or self.running[1].poll() is None:
            return []
        it, proc = self.running
        self.running = None
        value = robust_success(native_summary_path(run_dir, it)) if proc.returncode == 0 else None
        if value is None:  # a failed evaluation is no result; the next checkpoint is judged instead
            log.warning("race: native whole-clip evaluation of iteration %d failed (exit %s; %s)", it, proc.returncode,
                        Path(run_dir) / SIM2SIM_DIR / JUDGE_LOG)
            return []
        return [(it, value)]

    def poll(self, run_dir: str | Path, window_success: float) -> list[tuple[int, float]]:
        """After a window evaluation that scored `window_success`: the (iteration, robust whole-clip success)
        finished since the last call, and the next evaluation started if none runs."""
        run_dir = Path(run_dir)
        done = self._collect(run_dir)
        self.opened = self.opened or window_success >= self.after_success
        if self.opened and self.running is None and (newest := self._newest(run_dir)) is not None:
            it, onnx = newest
            self.running = (it, self._start(run_dir, it, onnx))
            self.started.append(it)
        return done

    def _start(self, run_dir: Path, iteration: int, onnx: Path) -> subprocess.Popen:
        """The child evaluating `onnx` (checkpoint `iteration`), its output appended to the judge's log."""
        out = native_summary_path(run_dir, iteration).parent
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(run_dir / SIM2SIM_DIR / JUDGE_LOG, "a") as f:  # the child keeps its own handle
            return subprocess.Popen(self.command(onnx, out), stdout=f, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL)

    def judge_now(self, run_dir: str | Path, iteration: int) -> float | None:
        """Evaluate checkpoint `iteration` and wait for it (the race's final policy, after its clock stopped);
        whatever runs is stopped first. None when it has no ONNX export or its evaluation failed."""
        self.close()
        run_dir = Path(run_dir)
        onnx = checkpoints_dir(run_dir) / motion_policy_onnx_name(iteration)
        if not onnx.is_file():
            return None
        code = self._start(run_dir, iteration, onnx).wait()
        return robust_success(native_summary_path(run_dir, iteration)) if code == 0 else None

    def close(self) -> None:
        """Stop a running evaluation (the race ended before it did)."""
        if self.running is not None:
            proc = self.running[1]
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
            self.running = None


__all__ = ["JUDGE_LOG", "NATIVE_MODEL", "NativeJudge", "native_summary_path", "robust_success"]
