"""The guarded reader of every JSON and YAML record (bmimic.runs.safe_read) and the Hydra settings that
keep a run's record its own (issue 77): no hang, no recursion, no expansion, no rewrite on refusal."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from bmimic.runs import safe_read
from bmimic.runs.folder import read_json, read_status
from tests.conftest import cli_env

DEEP = "[" * 5000 + "]" * 5000
BOMB = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join(['*' + p] * 10)}]\n" for p, c in zip("abcdefg", "bcdefgh"))


def test_nesting_depth_known_answers():
    assert safe_read.nesting_depth('{"a": [1, {"b": []}]}') == 4
    assert safe_read.nesting_depth('"[[[[" ') == 0  # brackets inside strings do not count
    assert safe_read.nesting_depth(r'["\"[[", [1]]') == 2  # nor after an escaped quote
    assert safe_read.nesting_depth(DEEP) == 5000


def test_deep_json_is_refused_not_a_recursion_error(tmp_path):
    with pytest.raises(safe_read.UnsafeFileError, match="nested deeper than 64"):
        safe_read.parse_json(DEEP, "x.json")
    assert safe_read.parse_json('{"a": [[[1]]]}') == {"a": [[[1]]]}
    status = tmp_path / "status.json"
    status.write_text(DEEP)
    assert read_json(status, default="unreadable") == "unreadable"
    assert read_status(tmp_path) == {"status": "missing"}


def test_fifo_and_device_are_refused_at_once(tmp_path):
    fifo = tmp_path / "status.json"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    with pytest.raises(safe_read.UnsafeFileError, match="not a regular file"):
        safe_read.read_text(fifo)
    assert read_status(tmp_path) == {"status": "missing"}
    link = tmp_path / "metrics.json"
    link.symlink_to("/dev/zero")
    with pytest.raises(safe_read.UnsafeFileError, match="not a regular file"):
        safe_read.read_json(link)
    assert time.monotonic() - t0 < 5  # an open that blocked would hang here forever


def test_size_limit(tmp_path):
    big = tmp_path / "big.json"
    big.write_text(json.dumps(list(range(1000))))
    with pytest.raises(safe_read.UnsafeFileError, match="more than the 100 a record"):
        safe_read.read_text(big, max_bytes=100)
    assert len(safe_read.read_json(big)) == 1000


def test_yaml_alias_bomb_and_depth_are_refused():
    with pytest.raises(safe_read.UnsafeFileError, match="aliases are expanded"):
        safe_read.parse_yaml(BOMB, "config.yaml")
    with pytest.raises(safe_read.UnsafeFileError, match="nested deeper"):
        safe_read.parse_yaml("a: " + "[" * 100 + "]" * 100, "config.yaml")
    assert safe_read.parse_yaml("a: &x 1\nb: *x\n") == {"a": 1, "b": 1}  # a few aliases are YAML as usual
    with pytest.raises(safe_read.UnsafeFileError, match="not valid YAML"):
        safe_read.parse_yaml("a: [", "config.yaml")


@pytest.mark.parametrize("override, needle", [
    ("hydra.output_subdir=.hydra", "hydra.output_subdir=.hydra: bmimic writes a run's launch record"),
    ("~hydra.callbacks.launch_guard", "the launch guard cannot be removed"),
])
def test_overrides_that_would_rewrite_a_record_are_refused_before_hydra_writes(tmp_path, override, needle):
    run = tmp_path / "run"
    run.mkdir()
    (run / "status.json").write_text('{"status": "done", "iteration": 2}')
    out = subprocess.run([sys.executable, "-m", "bmimic.train", "device=cpu", f"hydra.run.dir={run}", "resume=true",
                          override], capture_output=True, text=True, timeout=120, env=cli_env(), cwd=tmp_path)
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert out.returncode == 2 and len(errors) == 1 and needle in errors[0], out.stderr[-2000:]
    assert sorted(p.name for p in run.iterdir()) == ["status.json"]  # no .hydra/ written, nothing else
