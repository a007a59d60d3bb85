"""The README's "Your own study", end to end (issue 75): its sweep file (read from the README's yaml
block), the example clip of "Your own motion", the dry run that says a CPU would refuse the full
study, the sweep at smoke scale, and its report."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.conftest import REPO, cli_env

pytestmark = pytest.mark.slow

SMOKE = ["max_iterations=2", "seed=0", "device=cpu", "num_envs=2", "ppo.num_steps_per_env=8", "ppo.num_mini_batches=2",
         "eval.horizon_s=0.2", "eval.episodes_per_bin=1", "progress_bar=false", "logger=none"]


def _readme_section() -> str:
    text = (REPO / "README.md").read_text()
    return text.split("## Your own study", 1)[1].split("\n## ", 1)[0]


def _run(*args: str, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=cli_env(), capture_output=True, text=True,
                          timeout=900)


def test_the_readme_study_runs_end_to_end(tmp_path):
    section = _readme_section()
    study = re.search(r"```yaml\n(.*?)```", section, flags=re.S).group(1)
    assert "my_conf/sweep/my_study.yaml" in section and "'hydra.searchpath=[file://my_conf]'" in section
    (tmp_path / "my_conf" / "sweep").mkdir(parents=True)
    (tmp_path / "my_conf" / "sweep" / "my_study.yaml").write_text(study)
    search = "hydra.searchpath=[file://my_conf]"

    made = _run("bmimic.motion.example", "my_clip.csv", cwd=tmp_path)
    assert made.returncode == 0, made.stderr
    listed = _run("bmimic.launch", "list", "+sweep=my_study", search, "device=cpu", cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert "10 jobs (10 new)" in listed.stdout
    assert "this machine would refuse the sweep" in listed.stdout and "max_cpu_hours" in listed.stdout
    assert not (tmp_path / "outputs").exists()  # a dry run writes nothing

    trained = _run("bmimic.train", "-m", "+sweep=my_study", search, "motion=file", "motion.path=my_clip.csv", *SMOKE,
                   cwd=tmp_path)
    assert trained.returncode == 0, trained.stdout[-2000:] + trained.stderr[-2000:]
    sweep = tmp_path / "outputs" / "sweeps" / "my_study"
    runs = sorted(p.parent.parent.name for p in sweep.glob("*/seed=0/metrics.json"))
    assert len(runs) == 2 and any("sampler=uniform" in r for r in runs) and any("sampler=adaptive" in r for r in runs)

    report = _run("analysis.report", "outputs/sweeps/my_study", "--baseline", "sampler=uniform", cwd=tmp_path)
    assert report.returncode == 0, report.stderr
    text = (sweep / "report" / "report.md").read_text()
    assert "uniform" in text and "adaptive" in text


def test_an_unknown_key_in_your_own_study_is_one_line(tmp_path):
    (tmp_path / "my_conf" / "sweep").mkdir(parents=True)
    (tmp_path / "my_conf" / "sweep" / "my_study.yaml").write_text(
        "# @package _global_\nsweep_name: my_study\nmax_iteration: 1500\n")
    listed = _run("bmimic.launch", "list", "+sweep=my_study", "hydra.searchpath=[file://my_conf]", cwd=tmp_path)
    assert listed.returncode == 2
    err = listed.stderr.strip()
    assert err.startswith("error:") and err.count("\n") == 0 and "max_iteration" in err, err
    assert not (tmp_path / "outputs").exists()
