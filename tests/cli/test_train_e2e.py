"""End-to-end runs of the real command line on the CPU: train, checkpoint, resume, ONNX export."""

from __future__ import annotations

import json
import subprocess
import sys

import pandas as pd
import pytest
import torch

from tests.conftest import TINY, cli_env

pytestmark = pytest.mark.slow


def run_cli(args, cwd):
    out = subprocess.run([sys.executable, "-m", "bmimic.train", *args], cwd=cwd, capture_output=True, text=True,
                         timeout=900, env=cli_env())
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    run = root / "run"
    run_cli([*TINY, "ppo.save_interval=1", f"hydra.run.dir={run}", "sampler=adaptive", "eval.robust=true"], cwd=root)
    return run


def test_run_folder_contents(trained):
    for name in (".hydra/config.yaml", ".hydra/overrides.yaml", "provenance.json", "status.json", "metrics.json",
                 "train_metrics.parquet", "sampler.parquet", "eval.parquet", "motion_segments.json",
                 "checkpoints/latest.pt", "checkpoints/model_1.pt", "checkpoints/model_2.pt"):
        assert (trained / name).exists(), name
    status = json.loads((trained / "status.json").read_text())
    assert status["status"] == "done" and status["iteration"] == 2
    metrics = json.loads((trained / "metrics.json").read_text())
    assert metrics["iterations"] == 2 and metrics["env_steps"] == 2 * 2 * 8
    assert 0.0 <= metrics["final_eval_failure_rate"] <= 1.0
    train = pd.read_parquet(trained / "train_metrics.parquet")
    assert list(train["iteration"]) == [0, 1]
    # every reward and termination term of the run's config, and the tracking errors, one column each
    cfg = json.loads((trained / "resolved_config.json").read_text())
    terms = {f"reward/{t}" for t in cfg["env"]["rewards"]} | {f"termination/{t}" for t in cfg["env"]["terminations"]}
    assert terms and terms <= set(train.columns), terms - set(train.columns)
    assert {c for c in train.columns if c.startswith("metrics/")} == {
        "metrics/error_anchor_pos_m", "metrics/error_body_pos_m", "metrics/error_joint_pos_rad"}
    sampler = pd.read_parquet(trained / "sampler.parquet")
    assert {"iteration", "bin", "bin_start_s", "bin_end_s", "episodes", "failures", "raw_failure_rate",
            "smoothed_failure_rate", "probability"} <= set(sampler.columns)
    assert abs(sampler.groupby("iteration")["probability"].sum() - 1).max() < 1e-6
    assert sorted(set(sampler["iteration"])) == [0, 1] and len(sampler) == 2 * 10  # every iteration, 10 bins
    ev = pd.read_parquet(trained / "eval.parquet")
    assert ev["iteration"].max() == 2 and ev["failure_rate"].between(0, 1).all()
    assert (ev["visits"] >= ev["start_episodes"]).all() and (ev["failures"] <= ev["visits"]).all()
    robust = pd.read_parquet(trained / "eval_robust.parquet")  # eval.robust=true: once more, perturbed
    assert robust["iteration"].unique().tolist() == [2] and list(robust.columns) == list(ev.columns)
    assert 0.0 <= metrics["final_robust_eval_failure_rate"] <= 1.0


def test_released_bins_and_thinned_sampler_table(tmp_path):
    """sampler=beyondmimic trains on the released code's bins (10 s at 50 Hz: 500 // 50 + 1 = 11),
    which the diagnostics and the evaluation use too; log_every=2 keeps iterations 0, 2 and the last."""
    run = tmp_path / "run"
    overrides = [a for a in TINY if not a.startswith("max_iterations")]
    out = run_cli([*overrides, "max_iterations=4", "sampler=beyondmimic", "sampler.log_every=2",
                   "sampler.bin_size_seconds=0.5", f"hydra.run.dir={run}"], cwd=tmp_path)
    log = out.stdout + out.stderr
    assert "sampler beyondmimic (BeyondMimicSampler): 11 released bins" in log
    assert "update_every=step" in log and "does not apply to the released bins" in log
    sampler = pd.read_parquet(run / "sampler.parquet")
    assert sorted(set(sampler["iteration"])) == [0, 2, 3] and set(sampler["bin"]) == set(range(11))
    edges = sampler[sampler["iteration"] == 0]
    assert edges["bin_start_s"].iloc[1] == pytest.approx(46 / 50) and edges["bin_end_s"].iloc[-1] == 10.0
    ev = pd.read_parquet(run / "eval.parquet")
    assert set(ev["bin"]) == set(range(11))
    assert json.loads((run / "metrics.json").read_text())["num_bins"] == 11


def test_checkpoint_holds_sampler_and_rng(trained):
    ckpt = torch.load(trained / "checkpoints" / "latest.pt", weights_only=True)  # format 2: plain data only
    for key in ("actor_state_dict", "critic_state_dict", "optimizer_state_dict", "sampler", "rng", "progress"):
        assert key in ckpt
    assert ckpt["iter"] == 2
    assert "obs_normalizer._mean" in " ".join(ckpt["actor_state_dict"])  # normaliser statistics are saved


def test_onnx_export_with_metadata(trained):
    import onnx

    model = onnx.load(str(trained / "checkpoints" / "policy_2.onnx"))
    meta = {p.key: p.value for p in model.metadata_props}
    assert len(meta["joint_names"].split(",")) == 29
    assert len(meta["joint_stiffness"].split(",")) == 29 and meta["anchor_body_name"] == "torso_link"
    assert json.loads(meta["observation_layout"])[0]["name"] == "command"
    assert meta["policy_obs_dim"] == "160"


def test_resume_continues_iterations_lr_and_sampler(trained, tmp_path):
    before = torch.load(trained / "checkpoints" / "latest.pt", weights_only=True)  # format 2: plain data only
    run_cli([*[a for a in TINY if not a.startswith("max_iterations")], "max_iterations=3", "ppo.save_interval=1",
             f"hydra.run.dir={trained}", "sampler=adaptive", "eval.robust=true", f"resume={trained}"], cwd=tmp_path)
    after = torch.load(trained / "checkpoints" / "latest.pt", weights_only=True)  # format 2: plain data only
    assert after["iter"] == 3 and (trained / "checkpoints" / "model_3.pt").exists()
    train = pd.read_parquet(trained / "train_metrics.parquet")
    assert list(train["iteration"]) == [0, 1, 2]  # no duplicated or missing iterations
    assert before["iter"] == 2
    assert json.loads((trained / "status.json").read_text())["iteration"] == 3


def test_resume_restores_exact_state(trained, tmp_path):
    """Loading a checkpoint into a fresh trainer reproduces lr, iteration and sampler probabilities."""
    from bmimic.config import resolve_runtime
    from bmimic.task import build_evaluator, build_trainer, build_training
    from tests.conftest import compose

    cfg = compose([a for a in TINY if not a.startswith("progress")] + ["logger=none"])
    resolve_runtime(cfg, "cpu")
    training = build_training(cfg, "cpu")
    sampler, layout = training.sampler, training.task.layout
    trainer = build_trainer(training, build_evaluator(training.task), tmp_path)
    ckpt_path = trained / "checkpoints" / "model_2.pt"
    ckpt = torch.load(ckpt_path, weights_only=True)  # format 2: plain data only
    trainer.checkpoint.load_file(ckpt_path)
    assert trainer.progress.iteration == 2
    assert trainer.alg.learning_rate == pytest.approx(ckpt["optimizer_state_dict"]["param_groups"][0]["lr"])
    from bmimic.sampling.config import make_sampler

    ref = make_sampler(cfg.sampler, layout.num_bins, "cpu")
    ref.load_state_dict(ckpt["sampler"])
    assert torch.allclose(sampler.probabilities(), ref.probabilities())
    for key, value in ckpt["sampler"].items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(sampler.state_dict()[key], value), key
