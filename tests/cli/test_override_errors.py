"""Overrides that Hydra refuses are one `error:` line naming the override and exit status 2, from every
command that takes them (train, race, bench, launch list), where Hydra alone prints a 5-7 line block,
exits 1 and suggests `+key=...` for a typo, which bmimic then refuses as an unknown key."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bmimic.config import ConfigError, check_overrides
from tests.conftest import REPO

# override -> what its one line must say
BAD = {
    "sampler.gamm=0.5": "sampler.gamm: unknown key",
    "seed=1.5": "seed=1.5: Value '1.5' of type 'float' could not be converted to Integer",
    "progress_bar=maybe": "progress_bar=maybe: Value 'maybe' is not a valid bool",
    "run_name=dansé": "run_name=dansé: Hydra's override grammar takes a value with non-ASCII characters only in quotes",
    "motion=lafan_dance2": "motion=lafan_dance2: no such option of the config group motion; options: ",
    "seed=0,1": "seed=0,1: several values: a list is seed=[0,1]",
}


@pytest.mark.parametrize("override", sorted(BAD))
def test_a_refused_override_is_one_line_naming_it(override):
    with pytest.raises(ConfigError) as refused:
        check_overrides([override])
    message = str(refused.value)
    assert message.startswith(BAD[override]) and "\n" not in message
    assert "+sampler.gamm" not in message and "_schema" not in message  # no `+` advice, no schema entries


def test_what_composes_passes_and_a_quoted_non_ascii_value_is_read():
    cfg = check_overrides(["sampler=uniform", "motion.name='dansé'", "seed=3"])
    assert (cfg.sampler.name, cfg.motion.name, cfg.seed) == ("uniform", "dansé", 3)
    assert check_overrides(["-m", "seed=0,1"]) is not None  # a sweep's values: each job checks its own
    # another config tree: Hydra's to compose, only the grammar is checked (issue 77: Hydra's block, exit 1, before)
    assert check_overrides(["--config-path", "/elsewhere", "seed=1.5"]) is None
    with pytest.raises(ConfigError, match="a=b=c: not a valid override"):
        check_overrides(["--config-path", "/elsewhere", "a=b=c"])
    # bmimic's own tree named by -cp/-cn, or with a -cd folder searched beside it: checked as without them
    for flags in (["-cn", "train"], ["--config-path", str(REPO / "conf")], ["--config-dir", str(REPO)]):
        with pytest.raises(ConfigError, match="seed=1.5: Value '1.5'"):
            check_overrides([*flags, "seed=1.5"])


def _run(tmp_path, *argv: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([sys.executable, "-m", *argv], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.parametrize("argv", [
    ("bmimic.train", "sampler.gamm=0.5"),
    ("bmimic.train", "seed=1.5", "--cfg", "job"),
    ("bmimic.train", "progress_bar=maybe", "--help"),
    ("bmimic.train", "run_name=dansé"),
    ("bmimic.train", "-m", "+sweep=sampler_ablation", "seed=1.5,2"),
    ("bmimic.launch", "list", "+sweep=sampler_ablation", "progress_bar=maybe"),
    ("bmimic.race", "seed=1.5"),
    ("bmimic.bench", "--envs", "2", "--", "sampler.gamm=0.5"),
])
def test_every_entry_point_refuses_in_one_line_with_status_2(tmp_path, argv):
    out = _run(tmp_path, *argv)
    assert out.returncode == 2, (out.returncode, out.stderr[-2000:])
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), out.stderr
    bad = next(a for a in argv if "=" in a and not a.startswith("+sweep"))
    assert bad.split("=")[0] in lines[0] and "HYDRA_FULL_ERROR" not in out.stderr
    assert not (tmp_path / "outputs").exists()  # refused before anything was written


def test_a_race_that_could_time_no_evaluation_is_refused_before_it_trains(tmp_path):
    out = _run(tmp_path, "bmimic.race", "device=cpu")  # the CPU's smoke-scale 4 iterations, an evaluation every 100
    assert out.returncode == 2, out.stderr[-2000:]
    assert out.stderr.startswith("error: a race times evaluations, and with max_iterations=4 (the smoke-scale "
                                 "default on a CPU) and eval.every_iters=100 none would run")
    assert len(out.stderr.strip().splitlines()) == 1 and not (tmp_path / "outputs").exists()


@pytest.mark.parametrize("argv, words", [
    (["-cp", "/nonexistent"], "--config-path /nonexistent: no such folder"),
    (["--config-path=/nonexistent"], "--config-path /nonexistent: no such folder"),
    (["--config-path", "nowhere"], "--config-path nowhere: no such folder"),
    (["-cp", "pkg://no_such_package_x"], "--config-path pkg://no_such_package_x: no such Python package"),
    (["--config-name", "nope"], "--config-name nope: no nope.yaml in "),
    (["-cn", "nope.yaml"], "--config-name nope.yaml: no nope.yaml in "),
    (["-cd", "/nonexistent"], "--config-dir /nonexistent: no such folder"),
])
def test_a_config_folder_or_name_that_names_nothing_is_one_line_with_status_2(tmp_path, argv, words):
    """Issue 77: Hydra's block ("Primary config directory not found ...", "Cannot find primary config ...")
    and exit 1 became one line and exit 2, for train and race alike, before anything is written."""
    from tests.conftest import run_train

    code, out = run_train(*argv, "device=cpu", "max_iterations=1", cwd=tmp_path)
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert code == 2 and len(out.strip().splitlines()) == 1 and errors[0].startswith(f"error: {words}"), out
    assert list(tmp_path.iterdir()) == []
    from bmimic.config.sources import check_config_source

    for ok in (["-cp", str(REPO / "conf"), "--cfg", "job"], ["-cn", "train"], ["-cd", str(tmp_path)], ["seed=1"]):
        check_config_source(ok)  # what exists passes


@pytest.mark.slow
def test_race_refuses_a_config_name_that_names_nothing_in_one_line(tmp_path):
    out = _run(tmp_path, "bmimic.race", "--config-name", "nope")
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [
        f"error: --config-name nope: no nope.yaml in {REPO / 'bmimic' / 'conf'} (bmimic's primary config is train)"], \
        out.stderr


def test_info_of_a_sweep_shows_its_first_job(tmp_path):
    """Found by the generated harness at 500 examples (issue 77): `--info -m` put the first job's overrides
    after --info, which took the first of them as its value (two usage blocks, exit 2)."""
    from tests.conftest import run_train

    code, out = run_train("device=cpu", "max_iterations=1", "--info", "--multirun", cwd=tmp_path)
    assert code == 0 and "usage:" not in out and "Installed Hydra Plugins" in out, out[-2000:]
    assert not [line for line in out.splitlines() if line.startswith("error:") or ": error:" in line]
    assert list(tmp_path.iterdir()) == []


def test_launch_list_refuses_a_sweep_file_that_is_not_yaml_in_one_line(tmp_path):
    """Issue 77's second round: a sweep file of the user's own with a bracket left open or a YAML tag gave
    launch list an 85-line traceback (yaml's error escaped); bmimic.train -m already said it in one line."""
    for text in ("sweep_name: x\nmax_iterations: [2\n", "sweep_name: !custom x\n"):
        (tmp_path / "sweep").mkdir(exist_ok=True)
        (tmp_path / "sweep" / "x.yaml").write_text(text)
        out = _run(tmp_path, "bmimic.launch", "list", "+sweep=x", f"hydra.searchpath=[file://{tmp_path}]")
        assert out.returncode == 2 and out.stderr.startswith("error: ") and "x.yaml" in out.stderr, out.stderr
        assert len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stdout + out.stderr
