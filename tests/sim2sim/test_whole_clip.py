"""sim2sim's whole-clip rollouts: the robust condition's perturbations against the training env's
definitions (pushes, noise, domain randomisation, each undone after its rollout), the tables on
planted rollouts (survival, start transients, the gap), rollouts of a real exported policy on the
embedded clip, one-line refusals, and the command line on a tiny trained run."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pytest
import torch

from bmimic import sim2sim
from bmimic.runs.schema import START_TRANSIENT_S, WHOLE_CLIP_ROLLOUT_COLUMNS, WHOLE_CLIP_SURVIVAL_COLUMNS
from bmimic.sim2sim.perturb import Draw, Perturbations, Push, foot_geoms, perturbations_from_env
from bmimic.sim2sim.whole_clip import condition_summary, run_whole_clip, survival_table
from bmimic.sim2sim.whole_clip_gap import WarpWholeClip, gap_table
from tests.conftest import compose
from tests.sim2sim.test_sim2sim import run, task, trained, with_metadata  # noqa: F401  (fixtures)


@pytest.fixture(scope="module")
def policy(task):  # noqa: F811
    """(spec, reference, native model, motion ONNX path) of the fixture's random-weight policy."""
    path = task[2][1]
    spec = sim2sim.read_policy(path)
    ref = sim2sim.read_reference(sim2sim.policy_session(path), spec)
    return spec, ref, sim2sim.build_model(spec)[0], path


def _env_config() -> dict:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(compose(["device=cpu", "motion=easy_only"]).env, resolve=True)


# ============================================================================================ perturbations
def test_the_robust_condition_reads_the_training_configs_magnitudes(policy):
    spec = policy[0]
    env = _env_config()
    p = perturbations_from_env(env, spec, "test")
    # noise: each policy input term's half-width, by term name, on its slice
    offsets = np.cumsum([0] + [t.dim for t in spec.obs_terms])
    for term, lo, hi in zip(spec.obs_terms, offsets[:-1], offsets[1:]):
        assert (p.obs_noise[lo:hi] == float(env["policy_observations"][term.name]["noise"])).all(), term.name
    assert p.obs_noise.max() == 0.5 and (p.obs_noise == 0).any()  # joint_vel 0.5; command and actions clean
    (push,) = p.pushes
    assert push.interval_range_s == (1.0, 3.0) and push.lin_vel_mps.tolist() == [0.5, 0.5, 0.2]
    assert push.ang_vel_radps.tolist() == [0.52, 0.52, 0.78]
    assert p.foot_friction_range == (0.3, 1.6) and p.default_joint_offset_rad == 0.01
    assert [b for b, _ in p.com_offsets] == ["torso_link"] and p.com_offsets[0][1].tolist() == [0.025, 0.05, 0.05]
    assert p.applied == ["observation_noise", "foot_friction", "torso_com", "default_joint_pos", "push"] and not p.skipped
    # switched off as training switches them off; a user's event function has no native version
    off = perturbations_from_env({**env, "observation_noise": False, "events_enabled": False}, spec, "test")
    assert not off.obs_noise.any() and not off.pushes and off.applied == []
    events = {**env["events"], "push": {**env["events"]["push"], "enabled": False},
              "mine": {"func": "my_pkg.events:shake", "mode": "interval", "interval_range_s": [1, 2]}}
    some = perturbations_from_env({**env, "events": events}, spec, "test")
    assert not some.pushes and some.skipped == ["mine (my_pkg.events:shake, interval)"]


def test_a_push_is_the_training_envs_velocity_change(policy):
    from bmimic.envs.quat import quat_apply_inverse

    spec, ref, mjm, _ = policy
    rollout = sim2sim.Rollout(mjm, spec, ref)
    rollout.reset(200)
    push = Push("push", np.array([0.5, 0.5, 0.2]), np.array([0.52, 0.52, 0.78]), (1.0, 3.0))
    draw = Draw(Perturbations(np.zeros(spec.obs_dim), [push]), np.random.default_rng(3))
    before = rollout.d.qvel.copy()
    quat = rollout.d.qpos[3:7].copy()
    version = rollout._version
    draw.push(rollout, push)
    # the same uniform draws, in the order the push takes them: linear, then angular (world frame)
    u = np.random.default_rng(3).random(6)
    dv, dw = (2 * u[:3] - 1) * push.lin_vel_mps, (2 * u[3:] - 1) * push.ang_vel_radps
    expected_w = quat_apply_inverse(torch.tensor(quat[None]), torch.tensor(dw[None]))[0].numpy()
    np.testing.assert_allclose(rollout.d.qvel[:3] - before[:3], dv, atol=1e-12)
    np.testing.assert_allclose(rollout.d.qvel[3:6] - before[3:6], expected_w, atol=1e-12)
    assert (rollout.d.qvel[6:] == before[6:]).all() and draw.pushes == 1 and rollout._version > version


def test_interval_pushes_come_as_often_as_their_interval_and_reset_pushes_once(policy):
    spec, ref, mjm, _ = policy
    rollout = sim2sim.Rollout(mjm, spec, ref)
    rollout.reset(0)
    every_tenth = Push("a", np.full(3, 0.1), np.zeros(3), (0.1, 0.1))  # 5 control steps of 0.02 s
    at_start = Push("b", np.full(3, 0.1), np.zeros(3), None)
    draw = Draw(Perturbations(np.zeros(spec.obs_dim), [every_tenth, at_start]), np.random.default_rng(0))
    draw.after_reset(rollout)
    assert draw.pushes == 1  # the reset push
    for _ in range(50):
        draw.after_step(rollout)
    assert draw.pushes == 1 + 10
    # U(1, 3) s: 10 s of steps get between 3 and 10 pushes
    draw = Draw(Perturbations(np.zeros(spec.obs_dim), [Push("c", np.full(3, 0.1), np.zeros(3), (1.0, 3.0))]),
                np.random.default_rng(1))
    draw.after_reset(rollout)
    for _ in range(500):
        draw.after_step(rollout)
    assert 3 <= draw.pushes <= 10


def test_a_rollouts_randomisation_is_drawn_applied_and_taken_off_the_model_after_it(policy):
    spec, ref, mjm, _ = policy
    p = perturbations_from_env(_env_config(), spec, "test")
    rollout = sim2sim.Rollout(mjm, spec, ref)
    feet, torso = foot_geoms(mjm, spec), mjm.body("torso_link").id
    assert len(feet) >= 2
    friction, ipos = mjm.geom_friction.copy(), mjm.body_ipos.copy()
    draw = Draw(p, np.random.default_rng(5))
    draw.start(rollout)
    mu = mjm.geom_friction[feet, 0]
    assert np.all(mu == mu[0]) and 0.3 <= mu[0] <= 1.6 and mu[0] != friction[feet[0], 0]
    shift = mjm.body_ipos[torso] - ipos[torso]
    assert np.all(np.abs(shift) <= [0.025, 0.05, 0.05]) and np.abs(shift).min() > 0
    offset = rollout.default_joint_pos - spec.default_joint_pos
    assert np.abs(offset).max() <= 0.01 and np.abs(offset).min() > 0
    # the default pose's offset is the action offset and the joint observation's origin
    rollout.reset(100)
    clean = rollout.observation().copy()
    rollout.obs_noise = None
    bare = rollout.observation().copy()
    noise = clean[0] - bare[0]
    assert np.all(np.abs(noise) <= p.obs_noise + 1e-6) and np.all(noise[p.obs_noise == 0] == 0)
    assert np.abs(noise).max() > 0.1
    draw.finish(rollout)
    assert (mjm.geom_friction == friction).all() and (mjm.body_ipos == ipos).all()
    assert rollout.default_joint_pos is spec.default_joint_pos and rollout.obs_noise is None


# ============================================================================================ tables
def _planted_rollouts(fps: float = 50.0) -> pd.DataFrame:
    """Robust: 4 rollouts of a 10 s clip; one fails at 0.4 s (a start transient), one at 6.5 s, two complete.
    Nominal: one rollout, completed."""
    rows = []
    for condition, failures in (("robust", [0.4, 6.5, None, None]), ("nominal", [None])):
        for r, t in enumerate(failures):
            failed = t is not None
            rows.append({"condition": condition, "clip": 0, "clip_name": "dance", "rollout": r, "completed": not failed,
                         "failure_time_s": t if failed else math.nan, "transient": failed and t < START_TRANSIENT_S,
                         "pushes": 4, "failed": failed, "broken": False, "steps": int((t or 10.0) * fps),
                         "survival_s": t or 10.0, **{c: 30.0 + r for c in sim2sim.ERROR_NAMES}})
    return pd.DataFrame(rows)


def test_survival_over_clip_time_and_the_condition_summary_on_planted_rollouts():
    rows = _planted_rollouts()
    survival = survival_table(rows, np.array([10.0]))
    assert list(survival.columns) == list(WHOLE_CLIP_SURVIVAL_COLUMNS)
    robust = survival[survival["condition"] == "robust"].set_index("time_s")["tracking"]
    assert robust.index.tolist() == [float(t) for t in range(11)]  # every whole second, and the last frame at 10 s
    assert robust.tolist() == [4, 3, 3, 3, 3, 3, 3, 2, 2, 2, 2]
    assert survival[survival["condition"] == "nominal"]["tracking_frac"].eq(1.0).all()
    s = condition_summary(rows[rows["condition"] == "robust"])
    assert (s["rollouts"], s["completed"], s["success_rate"]) == (4, 2, 0.5)
    assert (s["failures"], s["transient_failures"], s["later_failures"]) == (2, 1, 1)
    assert s["mpkpe_rel_mm"] == pytest.approx(32.5)  # over the completed rollouts (30 + 2, 30 + 3), equal steps


def test_the_gap_compares_success_per_condition_and_clip_where_bmimic_has_one():
    rows = _planted_rollouts()
    warp = {"nominal": WarpWholeClip("eval/model_9", pd.DataFrame({"clip": [0], "rollouts": [16], "completed": [12]}))}
    gap = gap_table(rows, warp).set_index("condition")
    assert gap.loc["nominal", "sim2sim_success_rate"] == 1.0 and gap.loc["nominal", "warp_success_rate"] == 0.75
    assert gap.loc["nominal", "success_gap"] == pytest.approx(0.25) and gap.loc["nominal", "warp_source"] == "eval/model_9"
    assert gap.loc["robust", "sim2sim_success_rate"] == 0.5 and math.isnan(gap.loc["robust", "warp_success_rate"])


# ============================================================================================ rollouts
@pytest.fixture(scope="module")
def untermed(policy, tmp_path_factory):
    """The fixture's ONNX without termination terms: every rollout tracks (badly) to the clip's end."""
    return with_metadata(policy[3], tmp_path_factory.mktemp("noterm"), terminations="[]")


def test_whole_clip_rollouts_run_the_clip_from_its_first_frame_to_its_last(untermed):
    result = run_whole_clip(untermed, None, 2, ("nominal", "robust"), workers=1, seed=7)
    spec = sim2sim.read_policy(untermed)
    r = result.rollouts
    assert list(r.columns[:len(WHOLE_CLIP_ROLLOUT_COLUMNS)]) == list(WHOLE_CLIP_ROLLOUT_COLUMNS)
    assert r.groupby("condition").size().to_dict() == {"nominal": 1, "robust": 2}  # nominal: deterministic
    assert (r["start_frame"] == 0).all() and (r["end_frame"] == spec.num_frames - 1).all()
    assert (r["steps"] == spec.num_frames - 1).all() and r["completed"].all() and not r["failed"].any()
    robust = r[r["condition"] == "robust"]
    assert (robust["pushes"] >= 2).all() and (r.loc[r["condition"] == "nominal", "pushes"] == 0).all()
    # each robust rollout its own draw; none the nominal one
    errors = r[list(sim2sim.ERROR_NAMES)].to_numpy()
    assert len({tuple(np.round(e, 9)) for e in errors}) == 3
    s = result.summary["conditions"]
    assert s["robust"]["success_rate"] == 1.0 and s["robust"]["rollouts_per_clip"] == 2
    assert s["nominal"]["rollouts_per_clip"] == 1 and s["nominal"]["control_steps"] == spec.num_frames - 1
    assert result.summary["robust_perturbations"]["source"].startswith("bmimic's default env config")
    assert set(result.bins["condition"]) == {"nominal", "robust"}
    assert result.bins.groupby("condition")["visits"].sum().min() > 0
    # the same seed, the same draws: the robust rollouts repeat exactly; the nominal one is always the same
    again = run_whole_clip(untermed, None, 1, ("nominal", "robust"), workers=1, seed=7).rollouts
    cols = ["condition", "rollout", "steps", "pushes", *sim2sim.ERROR_NAMES]
    pd.testing.assert_frame_equal(again[cols], r[cols].iloc[:2].reset_index(drop=True))


def test_a_falling_policy_fails_at_a_frame_and_bin_the_tables_agree_on(policy):
    _, _, _, path = policy
    result = run_whole_clip(path, None, 1, ("nominal",), workers=1)
    row = result.rollouts.iloc[0]
    assert row["failed"] and not row["completed"]  # random weights fall within the 10 s clip
    assert row["failure_time_s"] == pytest.approx(row["failure_frame"] / 50.0)
    assert row["transient"] == (row["failure_time_s"] < START_TRANSIENT_S)
    bins = result.bins.set_index("bin")
    assert bins["failures"].sum() == 1 and bins.loc[row["failure_bin"], "failures"] == 1
    survival = result.survival.set_index("time_s")["tracking"]
    assert survival[survival.index < row["failure_time_s"]].eq(1).all()
    assert survival[survival.index >= row["failure_time_s"]].eq(0).all()


# ============================================================================================ command line
@pytest.mark.parametrize("args, message", [
    (["--whole-clip", "0"], "--whole-clip 0: the rollouts per clip must be >= 1"),
    (["--whole-clip", "-2"], "--whole-clip -2: the rollouts per clip must be >= 1"),
    (["--whole-clip", "1", "--conditions", "nominal,windy"], "'windy' unknown"),
    (["--whole-clip", "1", "--conditions", "robust,robust"], "without repeats"),
    (["--whole-clip", "1", "--horizon-s", "3"], "--horizon-s: the window evaluation's"),
    (["--conditions", "robust"], "--conditions: only with --whole-clip R"),
])
def test_bad_whole_clip_input_is_one_line_exit_2_and_writes_nothing(policy, tmp_path, capsys, args, message):
    out = tmp_path / "out"
    assert sim2sim.main([str(policy[3]), *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and len(err.splitlines()) == 1, err
    assert not out.exists()


@pytest.mark.slow
def test_the_command_writes_the_tables_and_the_gap_to_bmimics_own_whole_clip_evaluation(trained, tmp_path):  # noqa: F811
    # bmimic's own: episodes from every bin that run past the clip's end (the 10 s clip, 11 s horizon)
    run("bmimic.eval", trained, "--horizon-s", 11, "--episodes-per-bin", 2, "env.episode_length_s=12", cwd=tmp_path)
    before = {p: p.read_bytes() for p in (trained / "eval").rglob("*") if p.is_file()}
    out = run("bmimic.sim2sim", trained, "--whole-clip", 2, "--workers", 2, "--seed", 3, cwd=tmp_path)
    folder = trained / "sim2sim" / "bmimic_g1" / "model_2" / "whole_clip"
    names = sorted(p.name for p in folder.iterdir())
    assert names == ["eval_bins.parquet", "eval_episodes.parquet", "eval_segments.csv", "eval_summary.json",
                     "sim2sim_gap_clips.csv", "whole_clip_survival.csv"]
    summary = json.loads((folder / "eval_summary.json").read_text())
    rollouts = pd.read_parquet(folder / "eval_episodes.parquet")
    assert rollouts.groupby("condition").size().to_dict() == {"nominal": 1, "robust": 2}
    assert summary["seed"] == 3 and summary["robust_perturbations"]["source"].endswith("(env)")
    nominal = summary["conditions"]["nominal"]
    assert nominal["warp_source"].startswith(str(trained.resolve() / "eval" / "model_2"))
    warp = pd.read_parquet(trained / "eval" / "model_2" / "eval_episodes.parquet").query("bin == 0")
    assert nominal["warp_rollouts"] == len(warp) and nominal["warp_success_rate"] == pytest.approx(1 - warp["failed"].mean())
    gap = pd.read_csv(folder / "sim2sim_gap_clips.csv").set_index("condition")
    assert gap.loc["nominal", "success_gap"] == pytest.approx(nominal["success_gap"])
    assert math.isnan(gap.loc["robust", "warp_success_rate"])  # bmimic has no robust whole-clip evaluation here
    survival = pd.read_csv(folder / "whole_clip_survival.csv")
    last = survival.groupby("condition")["tracking_frac"].last()
    assert last.to_dict() == pytest.approx(rollouts.groupby("condition")["completed"].mean().to_dict())
    assert "completed the clip" in out.stdout and "gap" in out.stdout
    assert {p: p.read_bytes() for p in (trained / "eval").rglob("*") if p.is_file()} == before


def test_nominal_rollouts_repeat_exactly_in_native_mujoco(policy):
    """Why one nominal rollout stands for R: two runs of the same start are the same, step for step."""
    spec, ref, mjm, path = policy
    spec = dataclasses.replace(spec, terminations=[])
    rollout = sim2sim.Rollout(mjm, spec, ref, sim2sim.policy_session(path))
    a, b = (sim2sim.run_episode(rollout, 0, 60) for _ in range(2))
    assert np.array_equal(a.errors, b.errors) and a.row["steps"] == 60


def test_bmimics_own_whole_clip_evaluation_is_the_gaps_first_source(tmp_path):
    """bmimic.eval --whole-clip's tables (eval/<label>/whole_clip/) first, then training's whole_clip.parquet
    at the checkpoint's iteration; each condition it has, robust too."""
    from types import SimpleNamespace

    from bmimic.runs.folder import WHOLE_CLIP_DIR, WHOLE_CLIP_FILES, table_path
    from bmimic.sim2sim.whole_clip_gap import warp_whole_clip

    spec = SimpleNamespace(clip_starts=[0, 50], num_frames=120)
    rows = pd.DataFrame({"condition": ["nominal", "nominal", "robust", "robust"], "clip": [0, 1, 0, 1],
                         "rollouts": [1, 1, 8, 8], "completed": [1, 0, 6, 2]})
    pd.concat([rows.assign(iteration=100, env_steps=0), rows.assign(iteration=200, env_steps=0, completed=[1, 1, 8, 7])]
              ).to_parquet(table_path(tmp_path, "whole_clip"))
    from_training = warp_whole_clip(tmp_path, "model_200", 200, spec)
    assert sorted(from_training) == ["nominal", "robust"]
    assert from_training["robust"].clips["completed"].tolist() == [8, 7] and "iteration 200" in from_training["robust"].source
    assert warp_whole_clip(tmp_path, "model_300", 300, spec) == {}  # no evaluation at that iteration, nor any other source
    folder = tmp_path / "eval" / "model_200" / WHOLE_CLIP_DIR
    folder.mkdir(parents=True)
    rows.to_csv(folder / WHOLE_CLIP_FILES[0], index=False)
    (folder / WHOLE_CLIP_FILES[-1]).write_text("{}")
    from_eval = warp_whole_clip(tmp_path, "model_200", 200, spec)
    assert from_eval["robust"].clips["completed"].tolist() == [6, 2] and "bmimic.eval --whole-clip" in from_eval["robust"].source
    gap = gap_table(pd.DataFrame({"condition": "robust", "clip": [0, 0], "clip_name": "c0", "completed": [True, False]}),
                    from_eval).set_index("clip")
    assert gap.loc[0, "warp_success_rate"] == pytest.approx(0.75) and gap.loc[0, "success_gap"] == pytest.approx(-0.25)
