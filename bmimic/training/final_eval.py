"""The final evaluations a run owes after its last iteration (rank 0): the windows unless the last
iteration had them, the robust windows (eval.robust) and the whole clips (eval.whole_clip.at_end).

A job (bmimic.job) trains, then calls `final_evaluations`; the robust evaluator comes from the
composition root as a factory, so that this floor builds nothing of its own.
"""

from __future__ import annotations

import contextlib
import logging
import math
from typing import TYPE_CHECKING, Any, Callable

from bmimic.runs.schema import FINAL_METRICS
from bmimic.training.interrupts import StopNow, StopSignals
from bmimic.training.logger import final_evaluation_line

if TYPE_CHECKING:
    from bmimic.training.runner import Trainer

log = logging.getLogger("bmimic.train")  # the command line's logger, whichever entry point runs the job


def learn_and_evaluate(trainer: Trainer, main_rank: bool, robust_evaluator: Callable[[], Any],
                       stop: StopSignals | None) -> tuple[dict, dict]:
    """Train to the budget (or the race's stop), then the final evaluations rank 0 owes the run:
    (final summary, metrics.json's final_robust_* and final_whole_clip_*), both empty when a signal
    interrupted (trainer.interrupted). `robust_evaluator()` builds the robust evaluation's evaluator."""
    from bmimic.training.run_state import rng_untouched

    cfg, final, robust = trainer.cfg, dict[str, Any](), dict[str, Any]()
    try:
        trainer.learn(signals=stop)
        if trainer.interrupted:
            return final, robust
        with rng_untouched():  # drawing nothing of training's: a pause here resumes as one unbroken run
            final = trainer.progress.last_eval
            windows = trainer.record.last_iteration("eval") != trainer.progress.iteration
            if main_rank:  # (tens of seconds on a CPU that nothing else would account for)
                log.info(final_evaluation_line(windows, cfg.eval.robust, trainer.whole_clip is not None and
                                               cfg.eval.whole_clip.at_end))
            # Rank 0 alone evaluates (the evaluation env holds no collective): the other ranks release
            # their graphs and leave the process group meanwhile, and return NaN.
            if not main_rank:
                final = dict.fromkeys((name.removeprefix("final_") for name in FINAL_METRICS), math.nan)
            elif windows:
                # (a resume of a run that reached max_iterations already holds its final evaluation)
                final = trainer.evaluate()
            robust = robust_evaluation(trainer, robust_evaluator(), stop) if (cfg.eval.robust and main_rank) else {}
            whole_clip = trainer.whole_clip
            if whole_clip is not None and cfg.eval.whole_clip.at_end and (
                    trainer.record.last_iteration("whole_clip") != trainer.progress.iteration):
                trainer.evaluate_whole_clip()
            if trainer.last_whole_clip is not None and trainer.last_whole_clip[0] == trainer.progress.iteration:
                robust.update({f"final_{k}": v for k, v in trainer.last_whole_clip[1].items()})
    except StopNow:  # a signal during an evaluation (bmimic.training.interrupts): the iteration is kept
        trainer.interrupted = True
    return final, robust


def robust_evaluation(trainer: Trainer, evaluator, stop: StopSignals | None = None) -> dict:
    """`eval.robust`: the final evaluation again in `evaluator` (domain randomisation, noise and pushes
    on) -> eval_robust.parquet; returns its summary as metrics.json's `final_robust_eval_*`."""
    from bmimic.training.evaluator import summarize

    policy = trainer.alg.get_policy()
    policy.eval()
    p = trainer.progress
    with stop.at_once() if stop is not None else contextlib.nullcontext():  # a signal ends it at once
        per_bin = evaluator.evaluate(policy, p.iteration, p.env_steps, p.wall_time_s)
    trainer.record.write_table("eval_robust", per_bin)
    evaluator.env.close()
    summary = summarize(per_bin, prefix="robust_eval")
    log.info("robust eval at iteration %d: failure rate %.3f (clean: see eval.parquet)", p.iteration,
             summary["robust_eval_failure_rate"])
    return {f"final_{k}": v for k, v in summary.items()}
