"""Run folders: atomic writes, status and provenance files, seeding."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from bmimic import runtime
from bmimic.runs.folder import (
    atomic_write_json,
    atomic_write_text,
    read_status,
    write_provenance,
    write_status,
)
from bmimic.runtime import (
    SOURCE_COMMIT_ENV,
    THREAD_ENV,
    provenance,
    resolve_device,
    seed_everything,
    source_commit,
    use_cpu_threads,
)


def test_atomic_write_replaces_whole_file(tmp_path):
    path = tmp_path / "a" / "x.json"
    atomic_write_json(path, {"a": 1})
    atomic_write_json(path, {"b": 2})
    assert json.loads(path.read_text()) == {"b": 2}
    assert [p.name for p in path.parent.iterdir()] == ["x.json"]  # no temp files left behind


def test_json_files_are_valid_json_a_value_that_is_not_a_number_is_null(tmp_path):
    """Issue 47: metrics.json held a bare NaN (mean_episode_length when no episode ended), which strict
    JSON readers (jq, browsers, other languages) refuse."""
    path = tmp_path / "metrics.json"
    atomic_write_json(path, {"nan": float("nan"), "inf": [float("-inf"), 1.5], "f32": np.float32("nan"),
                             "f64": np.float64(2.0), "nested": {"x": float("inf"), "n": 3, "s": "NaN"}})

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    data = json.loads(path.read_text(), parse_constant=refuse)
    assert data == {"nan": None, "inf": [None, 1.5], "f32": None, "f64": 2.0, "nested": {"x": None, "n": 3, "s": "NaN"}}


def test_atomic_write_failure_keeps_old_content(tmp_path):
    path = tmp_path / "x.txt"
    atomic_write_text(path, "old")

    class Boom:
        def __str__(self):
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError):
        from bmimic.runs.folder import atomic_write

        atomic_write(path, lambda tmp: (open(tmp, "w").write("partial"), str(Boom())))
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["x.txt"]


def test_status_roundtrip(tmp_path):
    assert read_status(tmp_path)["status"] == "missing"
    write_status(tmp_path, "running", 3)
    assert read_status(tmp_path)["status"] == "running" and read_status(tmp_path)["iteration"] == 3
    write_status(tmp_path, "failed", 4, error="sampler.K: must be >= 1")
    st = read_status(tmp_path)
    assert st["status"] == "failed" and "sampler.K" in st["error"] and st["updated"]


def test_provenance_fields(tmp_path):
    info = provenance("cpu")
    write_provenance(tmp_path, info)
    on_disk = json.loads((tmp_path / "provenance.json").read_text())
    assert on_disk["git_commit"] == info["git_commit"]
    for key in ("git_commit", "git_dirty", "python", "versions", "command", "torch_precision", "device"):
        assert key in on_disk
    for lib in ("torch", "warp-lang", "mujoco", "mujoco-warp", "rsl-rl-lib"):
        assert on_disk["versions"][lib], lib
    assert provenance("cpu")["device"] == "cpu"


def test_a_tree_without_git_takes_its_commit_from_the_environment(monkeypatch, caplog):
    # git answers nothing, as in a copy of the tree without .git (the GPU machine's)
    monkeypatch.setattr(runtime, "_git", lambda *args: None)
    monkeypatch.delenv(SOURCE_COMMIT_ENV, raising=False)
    assert source_commit() == (None, None)
    monkeypatch.setenv(SOURCE_COMMIT_ENV, " 8D82203 ")
    assert source_commit() == ("8d82203", None)  # dirty is unknown, not False
    info = provenance("cpu")
    assert info["git_commit"] == "8d82203" and info["git_dirty"] is None
    monkeypatch.setenv(SOURCE_COMMIT_ENV, "main; rm -rf /")
    with caplog.at_level("WARNING", logger="bmimic.runtime"):
        assert source_commit() == (None, None)
    assert SOURCE_COMMIT_ENV in caplog.text and "not a git commit" in caplog.text


def test_git_wins_over_the_environment(monkeypatch):
    answers = {"rev-parse": "a" * 40, "status": " M bmimic/x.py"}
    monkeypatch.setattr(runtime, "_git", lambda *args: answers[args[0]])
    monkeypatch.setenv(SOURCE_COMMIT_ENV, "8d82203")
    assert source_commit() == ("a" * 40, True)
    answers["status"] = ""
    assert source_commit() == ("a" * 40, False)


def test_resolve_device():
    assert resolve_device("cpu") == "cpu"
    expected = "cuda:0" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto") == expected
    if not torch.cuda.is_available():
        from bmimic import BmimicError

        with pytest.raises(BmimicError, match="device=cuda"):
            resolve_device("cuda")


def test_a_cpu_run_uses_one_torch_thread_unless_the_environment_says_otherwise(monkeypatch):
    before = torch.get_num_threads()
    try:
        for name in THREAD_ENV:
            monkeypatch.delenv(name, raising=False)
        torch.set_num_threads(2)
        assert use_cpu_threads("cuda:0") is None and torch.get_num_threads() == 2  # a GPU run: torch's own
        assert use_cpu_threads("cpu") == 1 and torch.get_num_threads() == 1
        torch.set_num_threads(2)
        monkeypatch.setenv("OMP_NUM_THREADS", "2")
        assert use_cpu_threads("cpu") is None and torch.get_num_threads() == 2  # the user's choice stands
    finally:
        torch.set_num_threads(before)


def test_seed_reproducible_streams():
    def draw(seed):
        gen = seed_everything(seed)
        return (np.random.rand(3), torch.rand(3), torch.rand(3, generator=gen), __import__("random").random())

    a, b, c = draw(5), draw(5), draw(6)
    for x, y in zip(a, b):
        assert np.allclose(np.asarray(x), np.asarray(y))
    assert not np.allclose(np.asarray(a[1]), np.asarray(c[1]))
    assert not np.allclose(np.asarray(a[2]), np.asarray(a[1]))  # the sampler stream is distinct


def test_portable_path_names_a_folder_below_the_working_directory_relatively(tmp_path, monkeypatch):
    from bmimic.runs.folder import portable_path

    monkeypatch.chdir(tmp_path)
    assert portable_path(tmp_path / "outputs" / "runs" / "r1") == os.path.join("outputs", "runs", "r1")
    assert portable_path(tmp_path) == "."
    assert portable_path("/elsewhere/runs/r1") == "/elsewhere/runs/r1"  # outside: as given
    assert portable_path("outputs/r2") == "outputs/r2"
