"""sweeps/races_dance1_whole_clip.sh, issue 44's race matrix: every row is a race command that bmimic.race
accepts and whose overrides compose to that row's GPUs, envs, sampler and seed; a row not in it is one line."""

from __future__ import annotations

import shlex
import subprocess

from bmimic.race import parse_args, race_overrides
from tests.conftest import REPO, compose

PLAN = REPO / "sweeps" / "races_dance1_whole_clip.sh"


def _plan(*args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(PLAN), *args], capture_output=True, text=True, timeout=60,
                          env={"PATH": "/usr/bin:/bin", **env})


def _rows() -> list[list[str]]:
    listed = _plan("--list")
    assert listed.returncode == 0, listed.stderr
    return [line.split()[:5] for line in listed.stdout.splitlines() if line.strip()]


def test_the_matrix_covers_the_issues_gpu_counts_envs_and_samplers():
    rows = {r[0]: dict(kv.split("=", 1) for kv in r[1:5]) for r in _rows()}
    shapes = {(r["gpus"], r["num_envs_per_gpu"]) for r in rows.values()}
    assert {("1", "4096"), ("1", "8192"), ("2", "4096"), ("4", "4096"), ("4", "2048")} <= shapes
    assert {r["sampler"] for r in rows.values()} == {"adaptive", "adaptive_hybrid", "uniform"}
    for gpus in ("1", "2", "4"):  # two seeds of the best configuration of every GPU count
        hybrid = {r["seed"] for r in rows.values() if r["gpus"] == gpus and r["sampler"] == "adaptive_hybrid"}
        assert len(hybrid) >= 2, gpus


def test_every_row_is_a_race_that_composes_to_its_row():
    for row in _rows():
        name, gpus = row[0], int(row[1].split("=")[1])
        done = _plan(name, "--dry-run")
        assert done.returncode == 0, done.stderr
        command = shlex.split(done.stdout.strip().splitlines()[-1])
        assert command[:1] == (["torchrun"] if gpus > 1 else ["python"])
        if gpus > 1:
            assert command[command.index("--nproc_per_node") + 1] == str(gpus)
        args, rest = parse_args(command[command.index("bmimic.race") + 1:])
        assert args.native_whole_clip >= 1 and args.json.name.endswith(f"_race_{name}.json")
        cfg = compose([o for o in race_overrides(rest, native=True) if not o.startswith("hydra.")])
        expected = dict(kv.split("=", 1) for kv in row[1:5])
        assert (cfg.motion.name, cfg.sampler.name, str(cfg.num_envs), str(cfg.seed)) == (
            "lafan_dance1_full", expected["sampler"], expected["num_envs_per_gpu"], expected["seed"])


def test_the_judges_workers_follow_the_cores_unless_given():
    default = shlex.split(_plan("1x4096-hybrid-s0", "--dry-run").stdout.splitlines()[-1])
    given = shlex.split(_plan("1x4096-hybrid-s0", "--dry-run", JUDGE_WORKERS="5").stdout.splitlines()[-1])
    assert int(default[default.index("--native-whole-clip") + 1]) >= 1
    assert given[given.index("--native-whole-clip") + 1] == "5"


def test_an_unknown_row_is_one_error_line_and_exit_2():
    done = _plan("8x4096-hybrid-s0")
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.count("\n") == 1 and done.stderr.startswith("error: no row '8x4096-hybrid-s0'")
