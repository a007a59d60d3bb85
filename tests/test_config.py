"""Config tree: every option of every group composes; typos fail at composition; validation names the key."""

from __future__ import annotations

import subprocess
import sys

import pytest
from omegaconf import OmegaConf

from bmimic import BmimicError
from bmimic.config import ConfigError, resolve_runtime
from bmimic.config.checks import validate
from tests.conftest import CONF, compose, run_train

GROUPS = ["robot", "motion", "sampler", "ppo", "sim", "env", "eval"]
OPTIONS = [(g, p.stem) for g in GROUPS for p in sorted((CONF / g).glob("*.yaml"))]


def test_required_groups_exist():
    for group in ("robot", "motion", "sampler", "ppo"):
        assert list((CONF / group).glob("*.yaml")), group
    assert {p.stem for p in (CONF / "sampler").glob("*.yaml")} >= {"uniform", "adaptive", "beyondmimic"}


def test_defaults():
    cfg = compose()
    assert cfg.robot.name == "g1"
    assert cfg.motion.source == "builtin"
    # the literal design: no other reading beat it by the design-choice study's rule (issue 32)
    assert cfg.sampler.name == "adaptive"
    assert cfg.sampler.accounting.attribution == "start" and cfg.sampler.accounting.update_every == "iteration"
    assert cfg.ppo.num_steps_per_env == 24 and cfg.ppo.learning_rate == 1e-3 and cfg.ppo.entropy_coef == 0.005
    for key in ("seed", "device", "num_envs", "max_iterations", "run_name", "sweep_name"):
        assert key in cfg


@pytest.mark.parametrize("group,option", OPTIONS, ids=[f"{g}={o}" for g, o in OPTIONS])
def test_every_option_composes(group, option):
    cfg = compose([f"{group}={option}"])
    OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    assert cfg[group] is not None


@pytest.mark.parametrize(
    "override",
    ["sampler.gama=0.5", "sampler.K=three", "ppo.learning_rate=fast", "env.episode_length=10", "nonsense=1"],
)
def test_typos_and_wrong_types_fail_at_composition(override):
    with pytest.raises(Exception) as err:
        compose([override])
    assert override.split("=")[0].split(".")[-1] in str(err.value)


def _resolved(overrides):
    cfg = compose(overrides)
    resolve_runtime(cfg, "cpu")
    return cfg


def test_runtime_defaults_cpu_and_gpu():
    cpu = _resolved([])
    assert cpu.num_envs == 8 and cpu.max_iterations == 4 and cpu.device == "cpu"
    gpu = compose([])
    resolve_runtime(gpu, "cuda:0")
    assert gpu.num_envs == 4096 and gpu.max_iterations == gpu.ppo.max_iterations
    explicit = compose(["num_envs=16", "max_iterations=7"])
    resolve_runtime(explicit, "cuda:0")
    assert explicit.num_envs == 16 and explicit.max_iterations == 7
    assert cpu.eval.whole_clip.rollouts == 2 and gpu.eval.whole_clip.rollouts == 128  # issue 44: 1-2 on a CPU


BAD = [
    (["ppo.float32_matmul_precision=tf32"], "ppo.float32_matmul_precision"),
    (["num_envs=3", "ppo.num_mini_batches=4", "ppo.num_steps_per_env=5"], "ppo.num_mini_batches"),
    (["sampler.lambda_uniform=1.5"], "sampler.lambda_uniform"),
    (["sampler.lambda_uniform=-0.1"], "sampler.lambda_uniform"),
    (["sampler.gamma=0"], "sampler.gamma"),
    (["sampler.gamma=1.2"], "sampler.gamma"),
    (["sampler.K=0"], "sampler.K"),
    (["sampler.K=1000000000"], "sampler.K"),
    (["env.rewards.motion_body_pos.params.std=0"], "env.rewards.motion_body_pos.params.std"),
    (["env.terminations.anchor_pos.params.threshold_m=-1"], "env.terminations.anchor_pos.params.threshold_m"),
    (["sampler.bin_size_seconds=0"], "sampler.bin_size_seconds"),
    (["sampler.bin_size_seconds=31"], "sampler.bin_size_seconds"),
    (["sampler.alpha_smooth=0"], "sampler.alpha_smooth"),
    (["sampler.accounting.attribution=middle"], "sampler.accounting.attribution"),
    (["sampler.accounting.failure=sometimes"], "sampler.accounting.failure"),
    (["num_envs=0"], "num_envs"),
    (["sim.decimation=0"], "sim.decimation"),
    (["sim.timestep_s=-1"], "sim.timestep_s"),
    (["env.episode_length_s=0"], "env.episode_length_s"),
    (["env.rewards.action_rate.func=no_such_term"], "env.rewards.action_rate.func"),
    (["eval.horizon_s=0"], "eval.horizon_s"),
    (["logger=stdout"], "logger"),
    (["ppo.gamma=1.5"], "ppo.gamma"),
    (["eval.whole_clip.rollouts=0"], "eval.whole_clip.rollouts"),
    (["eval.whole_clip.conditions=[nominal,windy]"], "eval.whole_clip.conditions"),
    (["eval.whole_clip.conditions=[]"], "eval.whole_clip.conditions"),
    (["eval.every_iters=100", "eval.whole_clip.every_iters=150"], "eval.whole_clip.every_iters"),
    (["eval.whole_clip.max_share=0"], "eval.whole_clip.max_share"),
    (["eval.whole_clip.after_success=1.5"], "eval.whole_clip.after_success"),
    (["eval.whole_clip.max_clip_s=nan"], "eval.whole_clip.max_clip_s"),
]


@pytest.mark.parametrize("overrides,key", BAD, ids=[b[1] + ":" + b[0][-1] for b in BAD])
def test_validation_names_the_key(overrides, key):
    cfg = _resolved(overrides)
    with pytest.raises(Exception) as err:
        validate(cfg, motion_duration_s=30.0)
    assert key in str(err.value)
    assert "\n" not in str(err.value).strip()


def test_default_config_is_valid():
    validate(_resolved([]), motion_duration_s=30.0)


def test_an_in_process_train_warns_nothing_and_keeps_the_imported_module(recwarn):
    """The in-process CLI runs (run_train) execute bmimic.train as __main__ after other tests imported it:
    runpy must not warn about the imported copy, and that copy is back in sys.modules afterwards."""
    import bmimic.train as imported

    code, out = run_train("--help")
    assert code == 0, out
    assert [str(w.message) for w in recwarn if issubclass(w.category, RuntimeWarning)] == []
    assert sys.modules["bmimic.train"] is imported


def test_config_error_is_one_line_from_train(tmp_path):
    code, out = run_train("device=cpu", "sampler.lambda_uniform=2", "motion=easy_only",
                          f"hydra.run.dir={tmp_path}/run", cwd=tmp_path)
    assert code == 2, out[-2000:]
    last = out.strip().splitlines()[-1]
    assert last.startswith("error:") and "sampler.lambda_uniform" in last
    assert "Traceback" not in out
    assert not (tmp_path / "run").exists()  # a refused launch leaves no folder behind


@pytest.mark.slow
def test_help_lists_groups():
    out = subprocess.run([sys.executable, "-m", "bmimic.train", "--help"], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0
    for group in ("robot", "motion", "sampler", "ppo"):
        assert group in out.stdout
    for option in ("uniform", "adaptive", "beyondmimic"):
        assert option in out.stdout


@pytest.mark.slow
def test_cfg_job_prints_config():
    out = subprocess.run([sys.executable, "-m", "bmimic.train", "--cfg", "job", "sampler=uniform"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0
    printed = OmegaConf.create(out.stdout)
    assert printed.sampler.name == "uniform"


def test_sweep_folder_layout():
    cfg = compose(["sampler=uniform", "seed=3", "sweep_name=abl"], return_hydra_config=True)
    assert cfg.hydra.sweep.dir == "outputs/sweeps/abl"
    assert "seed" in cfg.hydra.job.config.override_dirname.exclude_keys


def test_reward_terms_are_overridable():
    cfg = _resolved(["env.rewards.alive.weight=1.0", "env.rewards.action_rate.weight=-0.01"])
    assert cfg.env.rewards.alive.func == "is_alive" and cfg.env.rewards.alive.weight == 1.0
    validate(cfg, motion_duration_s=30.0)
    assert _resolved([]).env.rewards.alive.weight == 0.0  # not a BeyondMimic term: off by default
    # The default MDP is BeyondMimic's as published (issue 22); env=tracking differs only in the
    # action-rate weight.
    default, lighter = _resolved([]).env, _resolved(["env=tracking"]).env
    assert default == _resolved(["env=beyondmimic"]).env
    assert default.rewards.action_rate.weight == -0.1 and lighter.rewards.action_rate.weight == -0.01
    lighter.rewards.action_rate.weight = -0.1
    assert lighter == default
    with pytest.raises(ConfigError, match="env.rewards.alive.func"):
        validate(_resolved(["env.rewards.alive.func=is_alivee"]), motion_duration_s=30.0)


@pytest.mark.parametrize("argv,composes", [
    (["motion.include={}", "+motion.include.x=1"], True),  # the parent made a mapping first
    (["+motion.include.x=1", "motion.include={}"], True),  # ... or after the addition on the line
    (["+motion.include.x=1", "motion.include={y: 2}"], False),  # then y meets the addition's struct node
    (["+motion.include.x=1", "motion.include=[a]"], False),  # a list over the added mapping
])
def test_an_addition_and_a_later_override_of_its_parent_compose_or_give_one_line(argv, composes):
    """Whatever the order of `+a.b.c=v` and an override of `a.b`, the command composes or refuses in one
    line naming an override; never OmegaConf's bare assertion (issue 47)."""
    from bmimic.config import ConfigError, check_additions, check_overrides

    if composes:
        check_additions(argv)
        assert check_overrides(argv).motion.include.x == 1
        return
    with pytest.raises(ConfigError) as refused:
        check_additions(argv)
        check_overrides(argv)
    line = str(refused.value)
    assert len(line.splitlines()) == 1 and line.startswith("motion.include")


def test_adding_a_key_under_a_null_node_is_one_line_not_omegaconfs_assertion():
    # OmegaConf fails with a bare AssertionError inside Hydra's composition (a traceback on the CLI).
    from bmimic.config import ConfigError, check_additions

    bad = "+env.events.torso_com.interval_range_s.extra_0=1"
    with pytest.raises(ConfigError, match=r"env\.events\.torso_com\.interval_range_s is null in the config"):
        check_additions(["sampler=uniform", bad])
    check_additions(["sampler=uniform", "+seed_note=1", "env.rewards.action_rate.weight=0"])  # nothing to refuse
    out = subprocess.run([sys.executable, "-m", "bmimic.train", bad, "--cfg", "job"], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 2 and out.stderr.startswith("error: " + bad) and len(out.stderr.splitlines()) == 1
    assert "Traceback" not in out.stderr


def test_a_run_records_the_values_of_its_interpolations():
    """Issue 47: .hydra/config.yaml held `seed: ${oc.env:SLURM_ARRAY_TASK_ID}`, which the tools reading the
    run resolve in their own environment (or cannot). The record takes each interpolated leaf's value
    from the resolved config; the reader's own keys (data.lafan_dir) and everything else stay."""
    from bmimic.config import interpolated_keys, recorded_config

    composed = {"seed": "${oc.env:SLURM_ARRAY_TASK_ID}", "num_envs": None, "data": {"lafan_dir": "${oc.env:X,null}"},
                "sampler": {"gamma": "${oc.decode:0.5}", "K": 5}, "run_name": "a-${seed}"}
    resolved = {"seed": 7, "num_envs": 8, "data": {"lafan_dir": "/mine"}, "sampler": {"gamma": 0.5, "K": 5},
                "run_name": "a-7"}
    assert interpolated_keys(composed) == ["seed", "sampler.gamma", "run_name"]
    assert recorded_config(composed, resolved) == {"seed": 7, "num_envs": None, "data": {"lafan_dir": "${oc.env:X,null}"},
                                                   "sampler": {"gamma": 0.5, "K": 5}, "run_name": "a-7"}
    assert composed["seed"].startswith("${")  # not changed in place


def test_a_training_reads_its_config_keys_once_and_still_checks_the_motion_fit(tmp_path, monkeypatch):
    """`python -m bmimic.train` merges its config into the schema once (check_composed, before the
    runtime fills in values); validate and build_task after it check values and the motion's fit only,
    and the motion's fit still refuses bins longer than the motion and a motion without a duration."""
    import bmimic.config.checks as checks
    from bmimic.task import build_task

    merges = []
    real = checks.check_known_keys
    monkeypatch.setattr(checks, "check_known_keys", lambda cfg: (merges.append(1), real(cfg)))
    code, out = run_train("device=cpu", "num_envs=2", "max_iterations=1", "ppo.num_steps_per_env=4",
                          "ppo.num_mini_batches=2", "motion=easy_only", "motion.duration_s=7", "eval.horizon_s=0.2",
                          "progress_bar=false", "logger=none", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert code == 0, out[-2000:]
    assert len(merges) == 1

    cfg = compose(["device=cpu", "num_envs=2", "motion=easy_only", "motion.duration_s=7"], return_hydra_config=True)
    checks.check_composed(cfg, cfg.hydra.runtime.choices)
    resolve_runtime(cfg, "cpu")
    validate(cfg, composed_checked=True)
    merges.clear()
    task = build_task(cfg, "cpu")
    assert merges == [] and task.layout.num_bins == 7
    with pytest.raises(BmimicError, match="bin_size_seconds"):  # 1 s bins on a motion of 0.5 s
        checks.check_motion_fit(cfg, 0.5)
    with pytest.raises(ConfigError, match="motion: has no duration"):
        checks.check_motion_fit(cfg, float("nan"))


def test_a_placed_job_config_is_resolved_validated_and_read_only():
    # compose -> resolve for this machine -> validate, once: afterwards nothing downstream may change it.
    from omegaconf import OmegaConf
    from omegaconf.errors import ReadonlyConfigError

    from bmimic.job import place_job

    cfg = compose(["device=cpu"])
    assert cfg.num_envs is None and not OmegaConf.is_readonly(cfg)
    placed, place = place_job(cfg)
    assert placed is cfg  # the same object, typed by its schema (bmimic.config.PlacedConfig)
    assert place.device == "cpu" and place.rank == 0
    assert cfg.num_envs is not None and cfg.eval.episodes_per_bin is not None  # the runtime's values
    assert OmegaConf.is_readonly(cfg)
    with pytest.raises(ReadonlyConfigError):
        cfg.num_envs = 8
    with pytest.raises(ReadonlyConfigError):
        cfg.sampler.gamma = 0.5


@pytest.mark.parametrize(("overrides", "ignored"), [
    # the library study sets motion and max_iterations at the top level too (for its torchrun jobs), so a
    # single run that names its sampler and seed follows every parameter of the sweep
    (["+sweep=lafan36_library", "sampler=gmt", "seed=0"], []),
    (["+sweep=lafan36_library"], ["sampler", "seed"]),
    # gamma's budget lives only in the sweep: a single run keeps its own unless it is given
    (["+sweep=gamma", "seed=1", "sampler.gamma=0.5"], ["max_iterations"]),
    (["+sweep=gamma", "seed=1", "sampler.gamma=0.5", "max_iterations=5000"], []),
    (["+sweep=gamma"], ["max_iterations", "seed", "sampler.gamma"]),
    ([], []),
])
def test_a_single_run_is_warned_of_exactly_the_sweep_parameters_it_does_not_follow(overrides, ignored):
    from bmimic.launch_guard import ignored_sweep_params

    assert ignored_sweep_params(compose(overrides, return_hydra_config=True)) == ignored


def test_a_single_run_of_a_study_names_the_parameters_it_ignores(tmp_path):
    from tests.conftest import TINY

    # TINY sets motion and max_iterations, so of gamma's parameters only sampler.gamma goes unfollowed
    code, out = run_train(*TINY, "+sweep=gamma", "seed=0", f"hydra.run.dir={tmp_path / 'run'}", "logger=none")
    assert code == 0, out
    assert "+sweep=gamma sweeps sampler.gamma, which only a multirun expands" in out
