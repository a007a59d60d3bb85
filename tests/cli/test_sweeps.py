"""Sweeps: the study files, the dry run, GPU slots, error history, and the multirun CLI end to end.

The fast tests compose configs (about a second each); the `slow` ones run real tiny sweeps through
`python -m bmimic.train -m` in a subprocess, one sweep at a time.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig
from hypothesis import given
from hypothesis import strategies as st
from omegaconf import OmegaConf, open_dict, read_write

import bmimic.config  # noqa: F401  (registers the config schemas, as bmimic.train does)
from analysis.index import SweepIndexCallback
from bmimic import CONF_DIR, BmimicError, launch
from bmimic.runs.folder import append_error_log
from bmimic.sweeping import gpu_slots
from bmimic.sweeping import jobs as sweep_jobs
from bmimic.sweeping.gpu_slots import (
    VisibleDevicesError,
    check_visible_devices,
    claim_slot,
    parse_visible_devices,
    slot_gpu,
    slot_order,
)
from bmimic.sweeping.jobs import list_jobs, sweep_overrides
from bmimic.training.session import note_previous_attempt
from tests.conftest import REPO, wait_for

SWEEPS = REPO / "sweeps"

# study -> (number of jobs, the keys its jobs vary besides the seed)
STUDIES = {
    "sampler_ablation": (2 * 5, {"sampler"}),
    "gamma": (5 * 5, {"sampler.gamma"}),
    "lambda": (5 * 5, {"sampler.lambda_uniform"}),
    "kernel": (4 * 5, {"sampler.K"}),
    "bin_size": (4 * 5, {"sampler.bin_size_seconds"}),
    "variants": (8 * 5, {"sampler", "sampler.accounting.attribution", "sampler.accounting.failure"}),
    "design_choices": (5 * 5, {"design_choice"}),
    "design_choices_dance1": (6 * 5, {"design_choice"}),
    "dance1_full": (2 * 5, {"sampler"}),
    "mdp_action_rate": (2 * 5, {"env"}),
    "library_lafan": (2 * 5, {"sampler.clip_balance"}),
    "peer_samplers": (8 * 5, {"sampler"}),  # the field's seven samplers and adaptive_hybrid (issue 32)
    "sensitivity_dance1": (2 * 5, {"sampler"}),
    "sensitivity_gamma": (5 * 3, {"sampler.gamma"}),
    "sensitivity_lambda": (4 * 3, {"sampler.lambda_uniform"}),
    "sensitivity_kernel": (3 * 3, {"sampler.K"}),
    "sensitivity_bin_size": (4 * 3, {"sampler.bin_size_seconds"}),
    "sensitivity_alpha": (3 * 3, {"sampler.alpha_smooth"}),
    "confirm_hybrid_dance1": (2 * 10, {"sampler"}),
    "hybrid_factorial_dance1": (2 ** 3 * 3, {"sampler.accounting.attribution", "sampler.gamma", "sampler.K"}),
    "lafan36_library": (5 * 2, {"sampler"}),
    "confirm_hybrid_fall1": (2 * 10, {"sampler"}),  # issue 76: the confirmatory test on a second clip
    "equivalence_bins_dance1": (2 * 10, {"sampler.bin_size_seconds"}),  # issue 76: pre-registered TOSTs
    "equivalence_K_dance1": (2 * 10, {"sampler.K"}),
    "finished_stage_dance1": (2 * 5, {"sampler"}),  # issue 76: the recommendation at the whole-clip stage
}
# One knob of a study at a time: these files write into the study's folder (one report covers every
# knob) and estimate effect sizes on 3 seeds per level, beside the study's 5-seed reference arms.
FACTORIALS = {"hybrid_factorial_dance1"}  # effects read from cell means: 3 seeds per cell
KNOB_FILES = {f"sensitivity_{knob}": "sensitivity_dance1" for knob in ("gamma", "lambda", "kernel", "bin_size", "alpha")}
# Each job an hour on 4 GPUs over several sittings: 2 seeds, the floor for the design and the best arm.
TWO_SEED_STUDIES = {"lafan36_library"}


def compose_study(study: str, *overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3", job_name="train"):
        return compose("train", overrides=[f"+sweep={study}", *overrides], return_hydra_config=True)


@pytest.fixture
def hydra_config_restored():
    """Leave Hydra's global HydraConfig as it was (tests below set it as a launcher would)."""
    saved = HydraConfig.instance().cfg
    yield
    HydraConfig.instance().cfg = saved


# --------------------------------------------------------------------------------------------- study files
def test_every_study_is_listed_and_linked():
    assert (CONF_DIR / "sweep").resolve() == SWEEPS.resolve()
    assert sweep_jobs.available_studies() == sorted(STUDIES)
    for path in SWEEPS.glob("*.yaml"):
        assert path.read_text().splitlines()[0] == "# @package _global_", path.name


@pytest.mark.parametrize("study", sorted(STUDIES))
def test_study_composes_and_expands(study):
    n_jobs, varied = STUDIES[study]
    cfg = compose_study(study)
    params = cfg.hydra.sweeper.params
    assert cfg.sweep_name == KNOB_FILES.get(study, study)
    assert {"motion", "max_iterations", "seed"} <= set(params)
    assert int(params.max_iterations) > 0
    # Arms are compared at equal iterations, with at least the 5 seeds bootstrap intervals need.
    assert "time_limit_s" not in params and cfg.time_limit_s is None
    fewest = 3 if study in KNOB_FILES or study in FACTORIALS else 2 if study in TWO_SEED_STUDIES else 5
    assert len(str(params.seed).split(",")) >= fewest
    for key, value in params.items():  # every key is a real config key or group option (typo guard)
        if (CONF_DIR / key).is_dir():
            for option in str(value).split(","):
                assert (CONF_DIR / key / f"{option}.yaml").is_file(), f"{study}: {key}={option}"
        else:
            assert OmegaConf.select(cfg, key, default="<missing>") != "<missing>", f"{study}: {key}"

    jobs = sweep_overrides([f"+sweep={study}"])
    assert len(jobs) == n_jobs
    assert len({tuple(j) for j in jobs}) == n_jobs
    keys = {o.split("=", 1)[0] for job in jobs for o in job}
    changing = {k for k in keys if len({o for job in jobs for o in job if o.startswith(k + "=")}) > 1}
    assert changing == varied | {"seed"}
    assert all(f"+sweep={study}" in job for job in jobs)


def test_knob_files_share_their_study_protocol():
    """A knob file changes one sampler key of the design and nothing of the protocol."""
    base = compose_study("sensitivity_dance1")
    for study in KNOB_FILES:
        cfg = compose_study(study)
        for key in ("num_envs", "eval.every_iters", "eval.episodes_per_bin", "env.rewards.action_rate.weight",
                    "ppo.save_interval"):
            assert OmegaConf.select(cfg, key) == OmegaConf.select(base, key), (study, key)
        params = cfg.hydra.sweeper.params
        assert (params.motion, int(params.max_iterations), params.sampler) == ("lafan_dance1_full", 1500, "adaptive")


def test_the_library_study_runs_as_single_torchrun_jobs_with_its_protocol(tmp_path, hydra_config_restored):
    """lafan36_library's jobs run one at a time under torchrun, without -m: the study file alone (no
    sweeper params) must give them the motion, MDP and budget its multirun jobs get, and a job pinned to
    its multirun folder is that job (launch list, the report's arms)."""
    cfg = compose_study("lafan36_library", "sampler=uniform", "seed=1")
    params = cfg.hydra.sweeper.params
    assert cfg.motion.name == params.motion == "lafan_folder" and cfg.max_iterations == int(params.max_iterations)
    assert cfg.env.rewards.action_rate.weight == -0.01 and cfg.sampler.name == "uniform"
    assert (cfg.num_envs, cfg.eval.every_iters, cfg.sampler.log_every) == (8192, 500, 500)
    header = (SWEEPS / "lafan36_library.yaml").read_text()
    assert 'RUN="outputs/sweeps/lafan36_library/motion=lafan_folder,sampler=$A/seed=$S"' in header
    _, jobs = list_jobs(["+sweep=lafan36_library", f"hydra.sweep.dir={tmp_path}"])
    assert jobs[0].run_dir == tmp_path / "motion=lafan_folder,sampler=adaptive" / "seed=0"  # the header's RUN


def test_confirmatory_study_uses_fresh_seeds():
    """The confirmatory test's seeds (10-19) are used by no other study on the same clip."""
    confirm = {int(s) for s in str(compose_study("confirm_hybrid_dance1").hydra.sweeper.params.seed).split(",")}
    assert confirm == set(range(10, 20))
    for study in set(STUDIES) - {"confirm_hybrid_dance1"}:
        params = compose_study(study).hydra.sweeper.params
        if params.motion == "lafan_dance1_full":
            assert not confirm & {int(s) for s in str(params.seed).split(",")}, study
    header = (SWEEPS / "confirm_hybrid_dance1.yaml").read_text()
    assert "PRE-REGISTERED RULE" in header and "184,756" in header


def test_the_equivalence_studies_use_seeds_no_other_dance1_study_uses():
    """Issue 76's equivalence tests and finished-stage comparison: fresh seeds on dance1 (20-29, 30-39,
    40-44), the rule (and an equivalence test's margin) in the header before any run."""
    seeds = {}
    for study in STUDIES:
        params = compose_study(study).hydra.sweeper.params
        if params.motion == "lafan_dance1_full":
            seeds[study] = {int(s) for s in str(params.seed).split(",")}
    assert seeds["equivalence_bins_dance1"] == set(range(20, 30)) and seeds["equivalence_K_dance1"] == set(range(30, 40))
    assert seeds["finished_stage_dance1"] == set(range(40, 45))
    for study in ("equivalence_bins_dance1", "equivalence_K_dance1", "finished_stage_dance1"):
        assert all(not seeds[study] & other for name, other in seeds.items() if name != study), study
        header = (SWEEPS / f"{study}.yaml").read_text()
        assert "PRE-REGISTERED RULE" in header and ("Margin: 0.01" in header) == ("equivalence" in study)


def test_command_line_sweep_replaces_the_study_params():
    jobs = sweep_overrides(["+sweep=sampler_ablation", "seed=7,8", "sampler=uniform", "max_iterations=3"])
    assert [sorted(j) for j in jobs] == [
        sorted(["motion=default", "max_iterations=3", "seed=7", "sampler=uniform", "+sweep=sampler_ablation"]),
        sorted(["motion=default", "max_iterations=3", "seed=8", "sampler=uniform", "+sweep=sampler_ablation"]),
    ]


# --------------------------------------------------------------------------------------------- dry run
def test_dry_run_lists_folders_and_status(tmp_path, hydra_config_restored):
    done = tmp_path / "motion=default,sampler=uniform" / "seed=0"
    done.mkdir(parents=True)
    (done / "status.json").write_text(json.dumps({"status": "done", "iteration": 10, "error": None}))
    sweep_dir, jobs = list_jobs(["+sweep=sampler_ablation", "seed=0", f"hydra.sweep.dir={tmp_path}"])
    assert sweep_dir == tmp_path
    assert [j.run_dir for j in jobs] == [done, tmp_path / "motion=default,sampler=adaptive" / "seed=0"]
    assert [(j.status, j.iteration) for j in jobs] == [("done", 10), ("new", None)]
    text = sweep_jobs.format_jobs(sweep_dir, jobs)
    assert "2 jobs (1 done, 1 new); a run would train 1 and skip 1 done" in text


def test_dry_run_names_the_base_arm(tmp_path, hydra_config_restored):
    _, jobs = list_jobs(["seed=0,1", f"hydra.sweep.dir={tmp_path}"])
    assert [j.run_dir.relative_to(tmp_path).as_posix() for j in jobs] == ["base/seed=0", "base/seed=1"]


def test_dry_run_cli(capsys, hydra_config_restored):
    assert launch.main(["list", "+sweep=kernel", "seed=0", "sampler.K=1,3"]) == 0
    out = capsys.readouterr().out
    assert "motion=default,sampler.K=1/seed=0" in out and "motion=default,sampler.K=3/seed=0" in out
    assert "2 jobs" in out
    assert launch.main(["list", "+sweep=no_such_study"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "sampler_ablation" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("study", ["sampler_ablation", "design_choices_dance1"])
def test_the_dry_run_composes_one_job_per_arm_and_gets_every_jobs_config(study, tmp_path, hydra_config_restored):
    """An arm's other seeds are its first job's config with their seed (bmimic.sweeping.jobs): the
    same config and folder as composing each job as the launcher does."""
    from bmimic.config import config_loader

    with config_loader() as loader:
        master, _ = sweep_jobs._expand(loader, "train", [f"+sweep={study}", f"hydra.sweep.dir={tmp_path}"])
        jobs = sweep_jobs.expand_jobs(loader, master)
        for job in jobs:
            cfg = loader.load_sweep_config(master, list(job.overrides))
            with open_dict(cfg):
                cfg.hydra.job.num = job.num
                cfg.hydra.job.id = f"{cfg.hydra.job.name}_{job.num}"
            HydraConfig.instance().set_config(cfg)
            assert str(job.run_dir) == f"{cfg.hydra.sweep.dir}/{cfg.hydra.sweep.subdir}"
            task = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
            assert OmegaConf.to_yaml(job.config) == OmegaConf.to_yaml(task), job.overrides


# ------------------------------------------------------------------------ a job folder of other settings
def _done_run(tmp_path: Path, *overrides: str) -> Path:
    """The first job's folder of `+sweep=sampler_ablation seed=0` as a run with `overrides` left it
    (done, on a CPU: its resolved_config.json as bmimic.job writes it)."""
    from bmimic.config import resolve_runtime

    _, jobs = list_jobs(["+sweep=sampler_ablation", "seed=0", f"hydra.sweep.dir={tmp_path}", *overrides])
    job = jobs[0]
    resolve_runtime(job.config, "cpu")
    job.run_dir.mkdir(parents=True)
    (job.run_dir / "status.json").write_text(json.dumps({"status": "done", "iteration": 4, "error": None}))
    (job.run_dir / "resolved_config.json").write_text(json.dumps(OmegaConf.to_container(job.config, resolve=True)))
    return job.run_dir


def test_every_key_left_out_of_job_folder_names_is_result_neutral_or_a_budget():
    from bmimic.runs.schema import LOGISTICS_KEYS
    from bmimic.training.resume import RESULT_NEUTRAL_KEYS, RESUME_BUDGET_KEYS

    # The seed and the study name make the folder; num_envs changes results and no resume may change it.
    # Every other key out of the names is classified, so a job folder's run is compared on the rest.
    assert set(LOGISTICS_KEYS) - {"seed", "sweep", "+sweep", "num_envs"} <= {*RESULT_NEUTRAL_KEYS, *RESUME_BUDGET_KEYS}


@pytest.mark.parametrize("study", ["mdp_action_rate", "design_choices_dance1", "peer_samplers",
                                   "confirm_hybrid_dance1", "sensitivity_dance1"])
def test_a_studys_committed_runs_are_its_jobs_for_todays_bmimic(study, tmp_path, hydra_config_restored):
    """Run again, a study would take its committed runs (docs/results/<study>/runs) as done, not as runs
    of other settings: a default that changes what a study trains must be pinned in its sweep file.
    (dance1_full's runs predate `motion` in its job folder names.)"""
    runs = REPO / "docs" / "results" / study / "runs"
    seed = min(int(p.name.split("=", 1)[1]) for p in runs.glob("*/seed=*"))
    _, jobs = list_jobs([f"+sweep={study}", f"seed={seed}", f"hydra.sweep.dir={runs}"])
    assert jobs and all(j.status == "done" for j in jobs), [(j.run_dir, j.status) for j in jobs]
    assert [j.differs for j in jobs] == [{}] * len(jobs)


def test_a_smoke_runs_folder_is_not_the_studys_job(tmp_path, hydra_config_restored):
    smoke = _done_run(tmp_path, "max_iterations=4")
    study = ["+sweep=sampler_ablation", "seed=0", f"hydra.sweep.dir={tmp_path}"]
    # The smoke command itself sees its own job, done.
    _, same = list_jobs([*study, "max_iterations=4"])
    assert same[0].differs == {} and "skip 1 done" in sweep_jobs.format_jobs(tmp_path, same)
    sweep_jobs.check_job_runs(same)
    # The study (10000 iterations) does not: its first job's folder holds a run of another budget.
    _, jobs = list_jobs(study)
    assert jobs[0].run_dir == smoke and jobs[0].differs == {"max_iterations": (4, 10000)}
    assert jobs[1].differs == {}
    text = sweep_jobs.format_jobs(tmp_path, jobs)
    assert "max_iterations 4 -> 10000" in text and "a run would refuse to start" in text
    with pytest.raises(sweep_jobs.SweepListError, match=r"job 0 .*max_iterations 4 -> 10000.*sweep_name=.*resume=true"):
        sweep_jobs.check_job_runs(jobs)
    # resume=true continues it with the study's budget (a budget key: a resume may change it).
    _, extend = list_jobs([*study, "resume=true"])
    sweep_jobs.check_job_runs(extend)
    assert "continuing 1 run with this budget" in sweep_jobs.format_jobs(tmp_path, extend)


def test_a_run_of_other_settings_than_its_budget_is_refused_even_with_resume(tmp_path, hydra_config_restored):
    _done_run(tmp_path, "num_envs=4")  # not a key a resume may change
    _, jobs = list_jobs(["+sweep=sampler_ablation", "seed=0", f"hydra.sweep.dir={tmp_path}", "resume=true"])
    assert jobs[0].differs == {"num_envs": (4, 8)}  # (8: this CPU's default, as the run saw it)
    with pytest.raises(sweep_jobs.SweepListError, match="num_envs") as refused:
        sweep_jobs.check_job_runs(jobs)
    assert "add resume=true" not in str(refused.value)


def test_the_dry_run_cli_lists_then_refuses_a_folder_of_other_settings(tmp_path, capsys, hydra_config_restored):
    _done_run(tmp_path, "max_iterations=4")
    assert launch.main(["list", "+sweep=sampler_ablation", "seed=0", f"hydra.sweep.dir={tmp_path}"]) == 2
    out, err = capsys.readouterr()
    assert "holds a run with other settings: max_iterations 4 -> 10000" in out
    assert err.startswith("error: job 0") and len(err.strip().splitlines()) == 1


def test_a_sweep_over_a_smoke_runs_folder_refuses_before_any_job_and_writes_nothing(tmp_path):
    smoke = _done_run(tmp_path / "sweep", "max_iterations=4")
    before = {p: p.read_bytes() for p in (tmp_path / "sweep").rglob("*") if p.is_file()}
    out = subprocess.run([sys.executable, "-m", "bmimic.train", "-m", "+sweep=sampler_ablation", "seed=0",
                          f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=tmp_path, capture_output=True, text=True,
                         timeout=300, env={**os.environ, "PYTHONPATH": str(REPO)})
    assert out.returncode == 2, out.stderr[-2000:]
    assert out.stderr.startswith("error: job 0") and len(out.stderr.strip().splitlines()) == 1
    assert str(smoke) in out.stderr and "max_iterations 4 -> 10000" in out.stderr
    after = {p: p.read_bytes() for p in (tmp_path / "sweep").rglob("*") if p.is_file()}
    assert after == before  # nothing written, nothing removed


def test_a_job_compares_a_done_run_on_its_own_device(tmp_path, hydra_config_restored):
    from bmimic.sweeping.jobs import done_run_differences

    run = _done_run(tmp_path, "max_iterations=4")
    cfg = compose_study("sampler_ablation", "seed=0", "sampler=uniform", "motion=default", "max_iterations=10000")
    assert done_run_differences(cfg, run).startswith("holds a run done with other settings (max_iterations 4 -> 10000")
    with read_write(cfg):
        cfg.max_iterations = 4
        assert done_run_differences(cfg, run) is False  # the same job: skipped as done
        cfg.max_iterations, cfg.resume = 6, "true"
        assert done_run_differences(cfg, run) is True  # resume=true: continued with the longer budget


# --------------------------------------------------------------------------------------------- GPU slots
def test_slot_arithmetic_known_answers():
    assert slot_order(0, 4) == [0, 1, 2, 3]
    assert slot_order(6, 4) == [2, 3, 0, 1]
    assert [slot_gpu(s, ["0", "1", "2", "3"]) for s in range(8)] == ["0", "1", "2", "3"] * 2
    assert [slot_gpu(s, ["4", "7"]) for s in range(4)] == ["4", "7", "4", "7"]  # 2 jobs per GPU
    assert parse_visible_devices("2,3") == ["2", "3"]
    assert parse_visible_devices(" GPU-ab12, GPU-cd34 ") == ["GPU-ab12", "GPU-cd34"]
    assert parse_visible_devices("") == [] and parse_visible_devices("-1") == []
    assert parse_visible_devices("0,-1,2") == ["0"]  # CUDA stops at the first invalid entry
    with pytest.raises(ValueError):
        slot_order(0, 0)
    with pytest.raises(ValueError):
        slot_gpu(0, [])


def test_a_gpu_named_twice_is_refused_in_one_line():
    for ok in ({}, {"CUDA_VISIBLE_DEVICES": ""}, {"CUDA_VISIBLE_DEVICES": "0,1,2,3"},
               {"CUDA_VISIBLE_DEVICES": "0,-1,0"}):  # CUDA stops reading at -1: no repeat it would see
        check_visible_devices(ok)
    with pytest.raises(VisibleDevicesError, match=r"^CUDA_VISIBLE_DEVICES=3,0,1,2,3: names GPU 3 twice") as e:
        check_visible_devices({"CUDA_VISIBLE_DEVICES": "3,0,1,2,3"})
    assert "\n" not in str(e.value) and "n_jobs" in str(e.value)


def test_a_gpu_named_twice_stops_a_sweep_before_anything_is_written(tmp_path):
    sweep = tmp_path / "dup"
    proc = subprocess.run(sweep_cmd(sweep, "seed=0"), cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "CUDA_VISIBLE_DEVICES": "0,0"})
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith("error: CUDA_VISIBLE_DEVICES=0,0: names GPU 0 twice")
    assert not sweep.exists()


@given(job=st.integers(0, 10_000), n_gpus=st.integers(1, 16), per_gpu=st.integers(1, 4))
def test_slot_order_is_a_rotation_covering_every_gpu(job, n_gpus, per_gpu):
    n_slots = n_gpus * per_gpu
    order = slot_order(job, n_slots)
    assert sorted(order) == list(range(n_slots)) and order[0] == job % n_slots
    gpus = [str(g) for g in range(n_gpus)]
    used = [slot_gpu(s, gpus) for s in range(n_slots)]
    assert all(used.count(g) == per_gpu for g in gpus)  # every GPU gets jobs_per_gpu slots


def test_claim_slot_never_hands_out_a_held_slot(tmp_path):
    first = claim_slot(tmp_path, job_num=1, num_slots=2)
    second = claim_slot(tmp_path, job_num=1, num_slots=2)  # its own slot 1 is held: takes slot 0
    assert first[0] == 1 and second[0] == 0
    assert claim_slot(tmp_path, job_num=0, num_slots=2) is None
    first[1].close()  # the worker holding slot 1 ended
    third = claim_slot(tmp_path, job_num=0, num_slots=2)
    assert third[0] == 1
    second[1].close()
    third[1].close()


def _set_job_hydra_config(tmp_path, launcher: str, job_num: int):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3", job_name="train"):
        cfg = compose("train", overrides=[f"hydra/launcher={launcher}", f"hydra.sweep.dir={tmp_path}"],
                      return_hydra_config=True)
    with read_write(cfg.hydra), open_dict(cfg.hydra):
        cfg.hydra.job.num = job_num
    HydraConfig.instance().set_config(cfg)


def test_joblib_workers_get_distinct_gpus(tmp_path, monkeypatch, hydra_config_restored):
    monkeypatch.setattr("tempfile.tempdir", str(tmp_path))  # lock files out of the real temp folder
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,5")
    monkeypatch.setattr(gpu_slots, "_claimed", {})
    _set_job_hydra_config(tmp_path, "joblib_gpus", job_num=2)  # n_jobs = 2 visible GPUs x 1
    assert gpu_slots.pin_job_to_gpu() == "4" and os.environ["CUDA_VISIBLE_DEVICES"] == "4"
    assert gpu_slots.pin_job_to_gpu() == "4"  # the same worker's next job keeps its GPU
    worker_one = gpu_slots._claimed

    # A second worker process (fresh state, same visible GPUs) whose first job would also map to slot 0.
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "4,5")
    monkeypatch.setattr(gpu_slots, "_claimed", {})
    _set_job_hydra_config(tmp_path, "joblib_gpus", job_num=4)
    assert gpu_slots.pin_job_to_gpu() == "5"
    worker_one["lock"].close()
    gpu_slots._claimed["lock"].close()


def test_basic_launcher_pins_nothing(tmp_path, monkeypatch, hydra_config_restored):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1")
    monkeypatch.setattr(gpu_slots, "_claimed", {})
    _set_job_hydra_config(tmp_path, "basic", job_num=1)
    assert gpu_slots.pin_job_to_gpu() is None and os.environ["CUDA_VISIBLE_DEVICES"] == "0,1"


# --------------------------------------------------------------------------------------------- resume, errors, index
def test_sweep_job_resumes_only_from_its_own_checkpoint(tmp_path):
    import torch

    from bmimic.training.resume import plan_run

    def checkpoint(path, iteration):
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"actor_state_dict": {}, "iter": iteration}, path)

    job, sibling = tmp_path / "arm" / "seed=1", tmp_path / "arm" / "seed=0"
    checkpoint(sibling / "checkpoints" / "latest.pt", 7)
    job.mkdir(parents=True)
    plan = plan_run("true", job, sweep_job=True)
    assert plan.state is None and plan.run_dir == job  # never a sibling job's checkpoint
    checkpoint(job / "checkpoints" / "latest.pt", 3)
    plan = plan_run("true", job, sweep_job=True)
    assert plan.run_dir == job and plan.continues and plan.state["iter"] == 3


def test_error_history_survives_retries(tmp_path):
    note_previous_attempt(tmp_path, {"status": "missing"})
    note_previous_attempt(tmp_path, {"status": "done"})
    assert not (tmp_path / "errors.log").exists()
    append_error_log(tmp_path, "attempt failed: RuntimeError: boom", "Traceback ...\nRuntimeError: boom\n")
    note_previous_attempt(tmp_path, {"status": "failed", "iteration": 0, "error": "RuntimeError: boom"})
    note_previous_attempt(tmp_path, {"status": "running", "iteration": 40, "updated": "t"})
    lines = (tmp_path / "errors.log").read_text().splitlines()
    heads = [line for line in lines if line.startswith("=== ")]
    assert len(heads) == 3
    assert "attempt failed: RuntimeError: boom" in heads[0] and "Traceback ..." in lines
    assert "retrying after a failed attempt" in heads[1] and "RuntimeError: boom" in heads[1]
    assert "stopped while running (iteration 40" in heads[2]


def test_index_callback_writes_the_index(tmp_path, capsys):
    from tests.analysis.synthetic_runs import make_sweep

    sweep = make_sweep(tmp_path)
    SweepIndexCallback().on_multirun_end(OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}}))
    index = pd.read_csv(sweep / "index.csv")
    assert len(index) > 0 and set(index["status"]) >= {"done"}
    assert capsys.readouterr().out == ""  # the closing line is the outcomes callback's, once
    SweepIndexCallback().on_multirun_end(OmegaConf.create({"hydra": {"sweep": {"dir": str(tmp_path / "none")}}}))


# --------------------------------------------------------------------------------------------- end to end (slow)
SMOKE = ["num_envs=2", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2", "motion=easy_only",
         "eval.every_iters=0", "eval.horizon_s=0.2", "ppo.save_interval=1", "progress_bar=false", "logger=none"]
# The keys conf/train.yaml keeps out of folder names (budgets and logistics, not arms).
NOT_ARM = ("num_envs", "progress_bar", "logger", "eval.every_iters", "ppo.save_interval", "max_iterations")
SMOKE_ARM = ",".join(sorted(o for o in SMOKE if o.split("=")[0] not in NOT_ARM))


def sweep_cmd(sweep_dir: Path, *overrides: str) -> list[str]:
    return [sys.executable, "-m", "bmimic.train", "-m", "+sweep=sampler_ablation", *SMOKE, *overrides,
            f"hydra.sweep.dir={sweep_dir}"]


def run_sweep(sweep_dir: Path, *overrides: str, timeout: float = 900, rc: int = 0) -> subprocess.CompletedProcess:
    proc = subprocess.run(sweep_cmd(sweep_dir, *overrides), cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == rc, proc.stderr[-3000:]
    return proc


def tree_hash(folder: Path, skip: tuple[str, ...] = ()) -> dict[str, str]:
    import hashlib

    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name not in skip}


def status(job: Path) -> dict:
    return json.loads((job / "status.json").read_text())


def arm_dir(sampler: str) -> str:
    return ",".join(sorted([*SMOKE_ARM.split(","), f"sampler={sampler}"]))


@pytest.mark.slow
def test_sweep_end_to_end(tmp_path):
    sweep = tmp_path / "ablation"
    run_sweep(sweep, "seed=0,1", "max_iterations=2")
    jobs = sorted(p.parent.relative_to(sweep).as_posix() for p in sweep.glob("*/seed=*/status.json"))
    expected = sorted(f"{arm_dir(s)}/seed={seed}" for s in ("uniform", "adaptive") for seed in (0, 1))
    assert jobs == expected and not any("sweep=" in j for j in jobs)
    assert (sweep / "multirun.yaml").is_file()
    for job in jobs:
        assert status(sweep / job)["status"] == "done"
        assert json.loads((sweep / job / "metrics.json").read_text())["iterations"] == 2
    index = pd.read_csv(sweep / "index.csv")
    assert sorted(index["job"]) == expected
    assert set(index["status"]) == {"done"} and set(index["seed"]) == {0, 1}
    assert set(index["sampler"]) == {"uniform", "adaptive"}
    assert index["final_eval_failure_rate"].notna().all() and index["git_commit"].notna().all()
    # ... and the real sweep becomes a report: every figure and table exists and is non-empty.
    report = subprocess.run([sys.executable, "-m", "analysis.report", str(sweep)], cwd=REPO, capture_output=True,
                            text=True, timeout=600)
    assert report.returncode == 0, report.stderr[-3000:]
    files = list((sweep / "report").iterdir())
    assert (sweep / "report" / "report.md").read_text().count("sampler=") >= 2
    assert len([f for f in files if f.suffix == ".png"]) >= 5 and len([f for f in files if f.suffix == ".csv"]) >= 5
    assert all(f.stat().st_size > 0 for f in files)


@pytest.mark.slow
def test_killed_sweep_resumes_and_skips_finished_jobs(tmp_path):
    sweep = tmp_path / "resume"
    overrides = ("sampler=uniform", "seed=0,1", "max_iterations=12")
    first, second = (sweep / arm_dir("uniform") / f"seed={s}" for s in (0, 1))
    proc = subprocess.Popen(sweep_cmd(sweep, *overrides), cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        # status.json's iteration moves once a periodic checkpoint and its tables are written
        wait_for(proc, lambda: status(first)["status"] == "done" and status(second)["status"] == "running"
                 and status(second)["iteration"] >= 1, "first job done, second job running with a checkpoint")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert status(second)["status"] == "running"  # killed: nothing could mark it done or failed
    assert (second / "checkpoints" / "latest.pt").exists()
    first_done = status(first)

    run_sweep(sweep, *overrides)
    assert status(first) == first_done  # skipped: status.json untouched
    assert status(second)["status"] == "done" and status(second)["iteration"] == 12
    assert "resumed from" in (second / "train.log").read_text()
    assert "stopped while running" in (second / "errors.log").read_text()
    iterations = pd.read_parquet(second / "train_metrics.parquet")["iteration"].tolist()
    assert iterations == list(range(12))  # no iteration lost or repeated across the kill
    index = pd.read_csv(sweep / "index.csv")
    assert len(index) == 2 and set(index["status"]) == {"done"}


@pytest.mark.slow
def test_failed_job_is_retried_and_its_error_kept(tmp_path):
    sweep = tmp_path / "failing"
    overrides = ("sampler=uniform", "seed=0", "max_iterations=1", "sampler.bin_size_seconds=60")  # motion: 10 s
    job = sweep / ",".join(sorted([*SMOKE_ARM.split(","), "sampler.bin_size_seconds=60", "sampler=uniform"]))
    job = job / "seed=0"
    first = run_sweep(sweep, *overrides, rc=1)  # every job runs, then the multirun exits non-zero
    assert status(job)["status"] == "failed" and "bin_size_seconds" in status(job)["error"]
    assert "1 job(s) failed" in first.stderr and "sampler.bin_size_seconds=60" in first.stderr
    run_sweep(sweep, *overrides, rc=1)
    log = (job / "errors.log").read_text()
    assert log.count("attempt failed:") == 2 and "sampler.bin_size_seconds" in log
    assert "retrying after a failed attempt" in log
    assert pd.read_csv(sweep / "index.csv")["status"].tolist() == ["failed"]


@pytest.mark.slow
def test_rerun_leaves_done_jobs_byte_identical_and_failures_exit_non_zero(tmp_path):
    sweep = tmp_path / "rerun"
    run_sweep(sweep, "sampler=uniform", "seed=0", "max_iterations=1")
    job = sweep / arm_dir("uniform") / "seed=0"
    before = tree_hash(job, skip=("train.log",))
    assert ".hydra/config.yaml" in before and "train_metrics.parquet" in before
    run_sweep(sweep, "sampler=uniform", "seed=0", "max_iterations=1")
    assert tree_hash(job, skip=("train.log",)) == before  # skipped: not even its .hydra/ is rewritten
    # resume=true continues what is unfinished: a job done at this very budget is skipped, untouched.
    resumed = run_sweep(sweep, "sampler=uniform", "seed=0", "max_iterations=1", "resume=true")
    assert "already done" in resumed.stdout + resumed.stderr and tree_hash(job, skip=("train.log",)) == before
    # A sweep whose jobs would be refused is refused whole, before any job runs (issue 36).
    bad = run_sweep(sweep, "sampler=uniform", "seed=0,1", "max_iterations=1", "+sampler.gama=0.5", rc=2)
    assert "error: job 0" in bad.stderr and "sampler.gama" in bad.stderr
    assert tree_hash(job, skip=("train.log",)) == before


@pytest.mark.slow
def test_a_job_being_trained_is_skipped_by_a_second_sweep(tmp_path):
    sweep = tmp_path / "locked"
    overrides = ("sampler=uniform", "seed=0", "max_iterations=30")
    job = sweep / arm_dir("uniform") / "seed=0"
    first = subprocess.Popen(sweep_cmd(sweep, *overrides), cwd=REPO, stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)
    try:
        wait_for(first, lambda: status(job)["status"] == "running", "the first sweep training its job")
        second = run_sweep(sweep, *overrides)
        assert first.poll() is None, "the first sweep must still be training for this test to mean anything"
        assert "being trained by another process" in second.stderr and "1 job: 1 locked" in second.stdout
    finally:
        _, err = first.communicate(timeout=900)
    assert first.returncode == 0, err[-3000:]
    assert status(job)["status"] == "done" and status(job)["iteration"] == 30
    assert pd.read_parquet(job / "train_metrics.parquet")["iteration"].tolist() == list(range(30))  # trained once
    assert not (job / "errors.log").exists()  # nobody wrote "killed" or a failure into it


@pytest.mark.slow
def test_submitit_local_launcher(tmp_path):
    sweep = tmp_path / "submitit"
    run_sweep(sweep, "sampler=adaptive", "seed=0", "max_iterations=1", "hydra/launcher=submitit_local",
              "hydra.launcher.timeout_min=15")
    job = sweep / arm_dir("adaptive") / "seed=0"
    assert status(job)["status"] == "done"
    assert (sweep / ".submitit").is_dir()  # the job ran through submitit, in its own process
    assert pd.read_csv(sweep / "index.csv")["status"].tolist() == ["done"]


def test_a_job_folder_stays_in_its_sweep_whatever_its_values_hold(tmp_path, hydra_config_restored):
    """Issue 47: `motion.path=../../x.npz` made a job folder outside its sweep (and outside outputs/), so
    the sweep's index was empty and its report found no run. A `.` or `..` part of a value is spelled
    %2E; a job whose folder would still lie outside is refused, and so is a sweep folder of the user's
    own files."""
    from bmimic.sweeping.jobs import SweepListError

    _, jobs = list_jobs(["seed=0", "motion=file", "motion.path=../../../x.npz", f"hydra.sweep.dir={tmp_path}"])
    (folder,) = [j.run_dir for j in jobs]
    assert folder.resolve().is_relative_to(tmp_path.resolve())
    assert folder.relative_to(tmp_path).as_posix() == "motion.path=../%2E%2E/%2E%2E/x.npz,motion=file/seed=0"
    (tmp_path / "mine.txt").write_text("the user's\n")
    with pytest.raises(BmimicError, match="hydra.sweep.dir=.*holds files that are not a bmimic sweep .mine.txt"):
        list_jobs(["seed=0", f"hydra.sweep.dir={tmp_path}"])
    (tmp_path / "multirun.yaml").write_text("{}\n")
    (tmp_path / "base" / "seed=0").mkdir(parents=True)
    (tmp_path / "base" / "seed=0" / "notes.txt").write_text("the user's\n")
    with pytest.raises(SweepListError, match=r"job 0 \(seed=0\): its folder .* holds files that are not a bmimic run"):
        list_jobs(["seed=0", f"hydra.sweep.dir={tmp_path}"])
