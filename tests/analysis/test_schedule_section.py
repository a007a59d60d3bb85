"""The report says whether a sampler's own schedule (EGM's annealing) had finished at the iteration it reads
(issue 76: a peer read at iteration 2038 of its 8,400 is not the peer its paper runs), on planted run folders."""

from __future__ import annotations

import json

import pandas as pd

from analysis.report_views import schedule_section


def _run(root, name: str, resolved: dict | None = None, composed: str | None = None) -> str:
    run = root / name
    (run / ".hydra").mkdir(parents=True)
    if resolved is not None:
        (run / "resolved_config.json").write_text(json.dumps(resolved))
    if composed is not None:
        (run / ".hydra" / "config.yaml").write_text(composed)
    return str(run)


def test_each_scheduled_arm_says_whether_its_schedule_had_finished(tmp_path):
    runs = pd.DataFrame({"arm": ["egm", "egm", "old_egm", "uniform"], "included": [True, True, True, True],
                         "run_dir": [
                             _run(tmp_path, "a", {"max_iterations": 900, "sampler": {"schedule_iterations": 1000}}),
                             _run(tmp_path, "b", {"max_iterations": 900, "sampler": {"schedule_iterations": 800}}),
                             # a record without a resolved config: null is the run's max_iterations
                             _run(tmp_path, "c", composed="max_iterations: 600\nsampler:\n  schedule_iterations: null\n"),
                             _run(tmp_path, "d", {"max_iterations": 900, "sampler": {"name": "uniform"}})]})
    lines = schedule_section(runs, 600)
    assert lines[0] == "## Samplers with schedules of their own"
    body = [line for line in lines if line.startswith("- ")]
    assert body == [
        "- `egm` anneals over 1000 iterations (sampler.schedule_iterations; its seeds' schedules: 800, 1000); at "
        "iteration 600, where this report reads it, its schedule had not finished: the report reads 60% of the way "
        "through it.",
        "- `old_egm` anneals over 600 iterations (sampler.schedule_iterations); at iteration 600, where this report "
        "reads it, its schedule had finished."]
    assert schedule_section(runs[runs["arm"] == "uniform"], 600) == []
