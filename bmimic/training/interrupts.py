"""Stopping a training run cleanly: Ctrl-C (SIGINT) and SIGTERM (how SLURM stops, cancels and
preempts a job) end the current iteration instead of the process.

While `StopSignals` is active, the first of these signals only sets `requested`; the training loop
checks it after each iteration, writes a checkpoint and the tables, and the run ends with status
`interrupted` and exit status 128 + signal (130, 143). A second one stops at once (the default action).
In a phase that may last minutes and has nothing to save midway (the set-up before the run writes
anything: motion, Warp kernel compilation, the rendezvous of torchrun's ranks; an evaluation), the
phase is marked `at_once`: the first signal raises `StopNow` there and then, so any phase ends within
seconds (an evaluation's iteration then gets its checkpoint, and the evaluation runs again on resume).
A signal a launcher already handles (submitit's SIGUSR1/SIGUSR2 before a SLURM time limit or on
preemption, which requeue the job) is caught the same way, and the launcher's handler runs after the
checkpoint (`chain`): the requeued job resumes from it and loses no iteration.

Torch-free. Handlers can only be set in the main thread; elsewhere nothing is installed.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from typing import Any, Iterator

from bmimic.cli.common import override_arg

log = logging.getLogger("bmimic.train")

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""Always caught while training."""
LAUNCHER_SIGNALS = tuple(s for s in (getattr(signal, "SIGUSR1", None), getattr(signal, "SIGUSR2", None)) if s)
"""Caught only where a launcher (submitit) installed a Python handler: theirs runs after the checkpoint."""


class StopNow(BaseException):
    """A stop signal arrived in a phase marked `at_once` (StopSignals): the phase ends here. A
    BaseException, so that no `except Exception` of the code it interrupts swallows it."""


class StopSignals:
    """Context manager: SIGINT/SIGTERM (and a launcher's signals) request a stop after the iteration,
    or at once in a phase marked `at_once`."""

    def __init__(self) -> None:
        self.signum: int | None = None
        """The first signal received (None: none)."""
        self.at_once_depth = 0
        """Phases marked at_once now entered (> 0: the first signal raises StopNow)."""
        self._previous: dict[int, Any] = {}

    def begin_at_once(self) -> None:
        """The phase that begins now ends at once on a signal (StopNow; at once, too, if one came already),
        until end_at_once."""
        if self.requested:
            raise StopNow
        self.at_once_depth += 1

    def end_at_once(self) -> None:
        """The phase begun by begin_at_once is over: a signal again stops after the iteration."""
        self.at_once_depth = max(self.at_once_depth - 1, 0)

    @contextlib.contextmanager
    def at_once(self) -> Iterator[None]:
        """A phase (begin_at_once ... end_at_once) as a `with` block."""
        self.begin_at_once()
        try:
            yield
        finally:
            self.end_at_once()

    @property
    def requested(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else ""

    @property
    def exit_code(self) -> int:
        """The shell's status of a process ended by the signal: 128 + its number."""
        return 128 + int(self.signum or 0)

    def __enter__(self) -> StopSignals:
        if threading.current_thread() is not threading.main_thread():
            return self
        for sig in (*STOP_SIGNALS, *LAUNCHER_SIGNALS):
            previous = signal.getsignal(sig)
            if sig in LAUNCHER_SIGNALS and not callable(previous):
                continue  # nobody handles it: its default action (terminate) stays
            self._previous[sig] = previous
            signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc: Any) -> None:
        for sig, previous in self._previous.items():
            signal.signal(sig, previous)
        self._previous.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is None:
            self.signum = signum
            if self.at_once_depth > 0:
                raise StopNow
            log.warning("%s: stopping after this iteration, with a checkpoint and the tables (send it again to "
                        "stop at once)", signal.Signals(signum).name)
            return
        # A second signal: the default action now (KeyboardInterrupt for SIGINT, termination otherwise).
        self.__exit__()
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)

    def chain(self) -> None:
        """Run the handler a launcher had installed for the received signal (submitit: requeue the job
        and exit); nothing for SIGINT/SIGTERM without one."""
        previous = self._previous.get(self.signum) if self.signum is not None else None
        self.__exit__()
        if callable(previous) and previous is not signal.default_int_handler:
            previous(self.signum, None)


class TrainingInterrupted(Exception):
    """Training stopped on a signal; the run holds a checkpoint and its tables (unless `iteration` is
    None: the signal came before anything was written)."""

    def __init__(self, stop: StopSignals, iteration: int | None, run_dir: Any) -> None:
        self.exit_code = stop.exit_code
        self.iteration = iteration
        self.run_dir = run_dir
        if iteration is None:
            message = f"interrupted by {stop.name} before training started; nothing was written"
        else:
            message = (f"interrupted by {stop.name} after iteration {iteration}: checkpoint and tables written to "
                       f"{run_dir}; continue with {override_arg('resume', run_dir)} (a sweep: run the same command again)")
        super().__init__(message)


__all__ = ["LAUNCHER_SIGNALS", "STOP_SIGNALS", "StopNow", "StopSignals", "TrainingInterrupted"]
