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


def test_regular_file_refuses_fifos_devices_and_links_out_of_the_run(tmp_path):
    """The one check before every binary reader of a run's files (torch.load, pyarrow, onnxruntime): a FIFO
    would block the reader, /dev/zero feed it forever, a link out of the run hand it another run's file."""
    run, other = tmp_path / "run", tmp_path / "other"
    (run / "checkpoints").mkdir(parents=True)
    other.mkdir()
    (run / "checkpoints" / "model_1.pt").write_bytes(b"x")
    (other / "model_2.pt").write_bytes(b"y")
    assert safe_read.regular_file(run / "checkpoints" / "model_1.pt", run) == run / "checkpoints" / "model_1.pt"
    (run / "checkpoints" / "latest.pt").symlink_to("model_1.pt")  # a link inside the run is the run's own
    assert safe_read.regular_file(run / "checkpoints" / "latest.pt", run)
    os.mkfifo(run / "train_metrics.parquet")
    (run / "eval.parquet").symlink_to("/dev/zero")
    (run / "checkpoints" / "model_2.pt").symlink_to(other / "model_2.pt")
    t0 = time.monotonic()
    for name, words in (("train_metrics.parquet", "not a regular file"), ("eval.parquet", "not a regular file"),
                        ("checkpoints/model_2.pt", "outside its run folder")):
        with pytest.raises(safe_read.UnsafeFileError, match=words):
            safe_read.regular_file(run / name, run)
    assert safe_read.regular_file(run / "checkpoints" / "model_2.pt")  # without a run: only the file's type
    with pytest.raises(FileNotFoundError):
        safe_read.regular_file(run / "nothing.pt", run)
    assert time.monotonic() - t0 < 5


def test_a_fifo_or_device_checkpoint_is_one_line_at_once(tmp_path):
    from bmimic.training.checkpoints import CheckpointError, load_checkpoint_file

    os.mkfifo(tmp_path / "model_1.pt")
    (tmp_path / "latest.pt").symlink_to("/dev/zero")
    t0 = time.monotonic()
    for name in ("model_1.pt", "latest.pt"):
        with pytest.raises(CheckpointError, match="not a regular file"):
            load_checkpoint_file(tmp_path / name)
    assert time.monotonic() - t0 < 5


@pytest.mark.parametrize("change, words", [
    (lambda w: w["mlp.0.weight"].fill_(float("nan")), "NaN or infinite"),
    (lambda w: w["mlp.0.bias"].__setitem__(0, float("inf")), "NaN or infinite"),
    (lambda w: w.__setitem__("mlp.0.weight", w["mlp.0.weight"].int()), "not a floating-point weight"),
    (lambda w: w.__setitem__("mlp.0.weight", [1.0]), "is not a tensor"),
])
def test_a_checkpoint_whose_weights_cannot_be_a_policy_is_refused(tmp_path, change, words):
    """Issue 77's second round: NaN weights evaluated to all-NaN tables (exit 0); an int32 weight was cast
    back silently by load_state_dict (another policy)."""
    import torch

    from bmimic.training.checkpoints import CheckpointError, load_checkpoint_file

    weights = {"mlp.0.weight": torch.ones(3, 2), "mlp.0.bias": torch.zeros(3), "normalizer.count": torch.tensor(4)}
    torch.save({"actor_state_dict": dict(weights), "iter": 2}, tmp_path / "good.pt")
    assert load_checkpoint_file(tmp_path / "good.pt")["iter"] == 2  # an integer buffer is no weight
    change(weights)
    torch.save({"actor_state_dict": weights, "iter": 2}, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match=words):
        load_checkpoint_file(tmp_path / "bad.pt")


@pytest.mark.parametrize("text", ['[{"a": NaN}]', '[Infinity]', '{"a": -Infinity}', '[1e999]'])
def test_finite_json_refuses_numbers_that_are_not_finite(text):
    with pytest.raises(safe_read.UnsafeFileError, match="not finite"):
        safe_read.parse_json(text, "bench.json", finite=True)
    safe_read.parse_json(text, "status.json")  # (the records' default reader keeps json's reading)
    assert safe_read.parse_json('[1, 2.5, -3e10]', finite=True) == [1, 2.5, -3e10]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    from tests.conftest import train_in_process

    root = tmp_path_factory.mktemp("tiny")
    return train_in_process(root / "run", "device=cpu", "num_envs=2", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2",
                            "motion=easy_only", "motion.duration_s=7", "eval.horizon_s=0.2", "progress_bar=false",
                            "logger=none", "max_iterations=1", cwd=root)


@pytest.mark.slow
@pytest.mark.parametrize("command, rel, how, words", [
    ("eval", "checkpoints/latest.pt", "outside", "outside its run folder"),
    ("eval", "checkpoints/latest.pt", "fifo", "not a regular file"),
    ("export", "checkpoints/latest.pt", "device", "not a regular file"),
    ("sim2sim", "checkpoints/motion_policy_1.onnx", "outside", "outside its run folder"),
    ("sim2sim", "checkpoints/motion_policy_1.onnx", "fifo", "not a regular file"),
    ("report", "eval.parquet", "outside", "eval.parquet refused: links to"),
    ("report", "train_metrics.parquet", "device", "no train_metrics.parquet"),
])
def test_readers_of_a_runs_binary_files_refuse_fifos_devices_and_links_out_of_the_run(tiny_run, tmp_path, capsys,
                                                                                      command, rel, how, words):
    """Issue 77: checkpoints/latest.pt linked to /dev/zero read forever, a FIFO blocked the reader, and a file
    linked from another run was read as this run's. Each reader checks with safe_read.regular_file first."""
    import importlib
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run, ignore=shutil.ignore_patterns("eval", "sim2sim", "report"))
    outside = tmp_path / ("elsewhere" + "".join((run / rel).suffixes))
    shutil.copy(run / rel, outside)
    (run / rel).unlink()
    {"outside": lambda p: p.symlink_to(outside), "fifo": os.mkfifo, "device": lambda p: p.symlink_to("/dev/zero")}[how](
        run / rel)
    if command == "eval" and rel.endswith("latest.pt"):
        (run / "checkpoints" / "model_1.pt").unlink()  # the newest checkpoint is the one damaged
    argv = {"eval": [str(run), "--episodes-per-bin", "1"], "export": [str(run), "--force"],
            "sim2sim": [str(run), "--episodes-per-bin", "1", "--workers", "1"],
            "report": [str(run), "--out", str(tmp_path / "report")]}[command]
    module = {"eval": "bmimic.eval", "export": "bmimic.export", "sim2sim": "bmimic.sim2sim.cli",
              "report": "analysis.report"}[command]
    t0 = time.monotonic()
    code = importlib.import_module(module).main(argv)
    err = capsys.readouterr().err
    assert time.monotonic() - t0 < 30
    if command == "report":  # lenient per run: listed as not included, with the reason
        import pandas as pd

        assert code == 0 and words in pd.read_csv(tmp_path / "report" / "runs.csv")["problem"][0], err
        return
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and words in errors[0], err
