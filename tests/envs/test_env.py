"""The tracking environment on the CPU: dimensions, consistent resets, sampler wiring, robustness."""

from __future__ import annotations

import math

import pytest
import torch

from bmimic.config import resolve_runtime
from bmimic.envs.resets import write_reference_state
from bmimic.runtime import seed_everything
from bmimic.task import build_evaluator, build_training
from tests.conftest import compose

# (device, sim.compile_env_step): on a GPU machine the same tests also run the CUDA-graph path,
# eager and fused by torch.compile.
SETUPS = [("cpu", False)] + ([("cuda:0", False), ("cuda:0", True)] if torch.cuda.is_available() else [])


@pytest.fixture(scope="module", params=SETUPS, ids=lambda s: f"{s[0]}{'-compiled' if s[1] else ''}")
def built(request):
    device, compiled = request.param
    seed_everything(0)  # the tests below must not depend on what ran before them
    # sampler=adaptive (the design), not the default: the accounting tests below plant start bins and
    # one update per iteration, which are the design's bookkeeping
    cfg = compose(["motion=easy_only", "num_envs=4", f"device={device}", f"sim.compile_env_step={compiled}",
                   "sampler=adaptive"])
    resolve_runtime(cfg, device)
    training = build_training(cfg, device)
    task = training.task
    evaluator = build_evaluator(task)
    return cfg, task.robot, task.motion, task.layout, training.sampler, training.env, evaluator


def test_graph_path_on_gpu(built):
    cfg, robot, motion, layout, sampler, env, _ = built
    assert (env._graphs is not None) == (env.device.type == "cuda")
    for _ in range(20):
        obs, rew, dones, extras = env.step(torch.randn(4, 29, device=env.device) * 0.1)
    assert torch.isfinite(obs["policy"]).all() and torch.isfinite(rew).all()
    assert (env.time_steps < env.segment_end).all()


def test_returned_observations_are_not_overwritten(built):
    """rsl-rl stores the observation it acted on after the next step: it must not change under it."""
    env = built[5]
    first = env.step(torch.zeros(4, 29, device=env.device))[0]
    kept = first["policy"].clone()
    env.step(torch.ones(4, 29, device=env.device) * 0.3)
    assert torch.equal(first["policy"], kept)


def test_undesired_contact_count_reads_only_active_slots(built):
    """Counts per world from the active contact slots; unused slots (stale ids, stale geoms) add nothing."""
    env = built[5]
    sim = env.sim
    saved = [x.clone() for x in (sim.nacon, sim.contact_geom, sim.contact_worldid)]
    from bmimic.envs.mdp.rewards import undesired_contacts

    undesired = env.bodies.undesired[env.bodies.geom_body]
    undesired_geom, other_geom = int(torch.nonzero(undesired)[0]), int(torch.nonzero(~undesired)[0])
    try:
        sim.nacon.fill_(3)
        sim.contact_geom[:, 0] = other_geom
        sim.contact_geom[:, 1] = undesired_geom  # every slot, used or not, names an undesired body
        sim.contact_worldid.fill_(0)
        sim.contact_worldid[:2] = 2
        sim.contact_geom[2, 1] = other_geom  # slot 2 (world 0): no undesired body
        counts = undesired_contacts(env)
        assert counts.tolist() == [0.0, 0.0, 2.0, 0.0]
    finally:
        for dst, src in zip((sim.nacon, sim.contact_geom, sim.contact_worldid), saved):
            dst.copy_(src)


def test_observation_and_action_dims(built):
    cfg, robot, motion, layout, sampler, env, _ = built
    obs = env.get_observations()
    assert obs["policy"].shape == (4, 160)  # BeyondMimic policy observation
    assert obs["critic"].shape == (4, 286)  # privileged critic observation
    assert env.num_actions == 29
    assert env.max_episode_length == 500  # 10 s at 50 Hz
    o, r, d, extras = env.step(torch.zeros(4, 29, device=env.device))
    assert r.shape == (4,) and d.shape == (4,) and extras["time_outs"].shape == (4,)
    assert torch.isfinite(o["policy"]).all() and torch.isfinite(r).all()


def test_reset_poses_are_consistent(built):
    """After a state write the body poses read in the same step match the new state (mjlab #1068)."""
    *_, evaluator = built
    env = evaluator.env
    frames = torch.arange(env.num_envs, device=env.device) * 37 % env.reference.num_frames
    env.reset_to_frames(frames)
    s = env.state
    assert torch.allclose(s.robot_body_pos, s.ref_body_pos, atol=2e-4)
    err = (s.robot_body_quat * s.ref_body_quat).sum(-1).abs()
    assert torch.allclose(err, torch.ones_like(err), atol=1e-4)
    # At the reference state every tracking reward is (numerically) 1.
    from bmimic.envs.mdp import rewards

    for fn in (rewards.motion_relative_body_position_error_exp, rewards.motion_relative_body_orientation_error_exp,
               rewards.motion_global_anchor_position_error_exp):
        assert torch.allclose(fn(env, std=0.3), torch.ones(env.num_envs, device=env.device), atol=1e-3)


def test_clip_end_teleports_consistently(built):
    cfg, robot, motion, layout, sampler, env, _ = built
    # Every env on the reference at the last frame of its clip, mid-episode (so none terminates now).
    last = env.segment_end - 1
    env.time_steps[:] = last
    write_reference_state(env.sim, env.reference, torch.ones_like(env.reached_clip_end), last)
    env.sim.forward_kinematics()
    env.episode_length_buf[:] = 10
    env.step(torch.zeros(4, 29, device=env.device))
    s = env.state
    # Every env was resampled: its anchor is within the RSI noise of the new reference, not stale.
    dist = (s.robot_anchor_pos - s.ref_anchor_pos)[:, :2].norm(dim=-1)
    assert (dist < 0.2).all(), dist
    assert (env.time_steps < env.segment_end).all()
    assert (env.episode_length_buf == 11).all()  # the episodes continued


def _on_reference(env, frames, mask=None):
    """Put the (masked) envs exactly on the reference at `frames`, mid-episode (counter 10)."""
    mask = torch.ones(env.num_envs, dtype=torch.bool, device=env.device) if mask is None else mask
    frames = frames.to(env.device)
    env.time_steps.copy_(torch.where(mask, frames, env.time_steps))
    env.segment_start.copy_(torch.where(mask, frames, env.segment_start))
    write_reference_state(env.sim, env.reference, mask, env.time_steps)
    env.episode_length_buf.masked_fill_(mask, 10)
    env.sim.forward_kinematics()


def _fall(env, envs):
    """Pelvis on the floor: these envs end by the anchor-height termination in the next step."""
    env.sim.qpos[envs, 2] = 0.2
    env.sim.forward_kinematics()


def _fresh_iteration(env):
    env.end_rollout()
    env.pop_iteration_stats()


def test_failures_reach_the_sampler(built):
    cfg, robot, motion, layout, sampler, env, _ = built
    assert cfg.sampler.accounting.attribution == "start" and cfg.sampler.accounting.update_every == "iteration"
    _fresh_iteration(env)
    fps = int(motion.fps)
    _on_reference(env, torch.full((4,), 5 * fps + 5))
    env.feedback.start_bin.fill_(3)  # episodes that started in bin 3 ...
    _fall(env, slice(None))  # ... and fail now, in bin 5
    before = sampler.smoothed_failure().clone()
    _, _, dones, extras = env.step(torch.zeros(4, 29, device=env.device))
    assert dones.all() and extras["terminated"].all()
    env.end_rollout()
    after = sampler.smoothed_failure()
    assert after[3] > before[3], (after, before)
    stats = env.pop_iteration_stats()
    assert stats["bin_failures"][3] == 4 and stats["bin_episodes"][3] == 4 and stats["bin_failures"].sum() == 4
    assert stats["failures"] >= 4


def test_sampling_distribution_is_fixed_within_an_iteration(built):
    """update_every=iteration: steps with failures leave P alone; end_rollout makes one update
    from all of them."""
    cfg, robot, motion, layout, sampler, env, _ = built
    from bmimic.sampling import make_sampler

    _fresh_iteration(env)
    state, probs = sampler.state_dict(), sampler.probabilities()
    for k in range(3):
        _on_reference(env, torch.arange(4) * 2 * int(motion.fps) + 7 * k)
        _fall(env, [k, 3])
        env.step(torch.zeros(4, 29, device=env.device))
        assert torch.equal(sampler.probabilities(), probs), k
    env.end_rollout()
    assert not torch.equal(sampler.probabilities(), probs)
    stats = env.pop_iteration_stats()
    assert stats["bin_failures"].sum() >= 6 and stats["bin_episodes"].sum() >= 6
    ref = make_sampler(cfg.sampler, layout.num_bins, env.device)
    ref.load_state_dict(state)
    ref.update_counts(torch.as_tensor(stats["bin_episodes"]), torch.as_tensor(stats["bin_failures"]))
    assert torch.allclose(sampler.probabilities(), ref.probabilities(), rtol=0, atol=1e-12)


def test_start_bins_survive_clip_end_resamples_and_partial_resets(built):
    cfg, robot, motion, layout, sampler, env, _ = built
    acc = env.feedback
    _fresh_iteration(env)
    zeros = torch.zeros(4, 29, device=env.device)
    last = int(env.reference.frame_clip_end[0]) - 1
    fps = int(motion.fps)
    # Envs 0 and 1 on their clip's last frame (the reference resamples next step, the episode goes
    # on); envs 2 and 3 mid-clip. Each env's episode planted as started in a bin it is not in now.
    _on_reference(env, torch.tensor([last, last, 5 * fps + 3, 8 * fps + 3]))
    planted = torch.tensor([2, 4, 6, 1], device=env.device)
    acc.start_bin.copy_(planted)
    _, _, dones, _ = env.step(zeros)
    assert not dones.any() and (env.episode_length_buf == 11).all()
    assert (env.time_steps[:2] < last).all()  # envs 0 and 1 were resampled ...
    assert acc.start_bin.tolist() == planted.tolist()  # ... and kept their episodes' start bins
    # A partial reset: envs 0 and 2 fail; 1 and 3 go on, back on the reference.
    _on_reference(env, env.time_steps.clone(), torch.tensor([False, True, False, True], device=env.device))
    _fall(env, [0, 2])
    _, _, dones, extras = env.step(zeros)
    assert dones.tolist() == [1, 0, 1, 0] and extras["terminated"].tolist() == [True, False, True, False]
    env.end_rollout()
    stats = env.pop_iteration_stats()
    expected = [0.0] * layout.num_bins
    expected[2] = expected[6] = 1.0  # the planted start bins of envs 0 and 2, not where they failed
    assert stats["bin_episodes"].tolist() == expected and stats["bin_failures"].tolist() == expected
    # The reset envs start new episodes in the bins drawn for them; the others keep theirs.
    assert acc.start_bin[[1, 3]].tolist() == [4, 1]
    assert torch.equal(acc.start_bin[[0, 2]], layout.bins_of(env.segment_start[[0, 2]]))
    # Env 1, resampled at the clip end one step earlier, fails now: it counts for bin 4.
    _on_reference(env, env.time_steps.clone())
    _fall(env, [1])
    _, _, dones, _ = env.step(zeros)
    assert dones.tolist() == [0, 1, 0, 0]
    env.end_rollout()
    stats = env.pop_iteration_stats()
    assert stats["bin_episodes"].tolist() == [1.0 if b == 4 else 0.0 for b in range(layout.num_bins)]


def test_nonfinite_world_is_reset_not_fatal(built):
    cfg, robot, motion, layout, sampler, env, _ = built
    env.sim.qvel[1, :] = float("nan")
    obs, rew, dones, extras = env.step(torch.zeros(4, 29, device=env.device))
    assert torch.isfinite(obs["policy"]).all() and torch.isfinite(rew).all()
    assert dones[1] == 1 and extras["time_outs"][1]
    assert env.pop_iteration_stats()["nonfinite_resets"] >= 1


def test_uniform_and_eval_envs(built):
    *_, evaluator = built
    env = evaluator.env
    assert not env.events.model_fields and not env.events.has_interval and not env.observations.noisy["policy"]
    per_bin = evaluator.evaluate(lambda obs, stochastic_output=False: torch.zeros(env.num_envs, 29, device=env.device), 0, 0, 0.0)
    assert len(per_bin) == evaluator.layout.num_bins
    assert per_bin["failure_rate"].between(0, 1).all()
    assert (per_bin["mpkpe_mm"] >= 0).all() and per_bin["mpkpe_mm"].map(math.isfinite).all()


def test_step_traces_as_single_graphs(built):
    """The torch parts of a step trace without graph breaks: no host synchronisation (`.item()`,
    data-dependent shapes) and no OmegaConf access on the step path. That is what lets
    `sim.compile_env_step` fuse them and CUDA graphs replay them."""
    import torch._dynamo as dynamo
    from omegaconf import DictConfig

    env = built[5]
    if env.device.type != "cpu":
        pytest.skip("tracing is device-independent; checked once on the CPU")
    assert not isinstance(env.cfg, DictConfig)
    for part in (env._pre_physics, env._post_physics, env._observe):
        explained = dynamo.explain(part)()
        reasons = [b.reason.splitlines()[0] for b in explained.break_reasons]
        # break_reasons also lists a break at the very end (e.g. a trailing `.item()`), which
        # graph_break_count does not count.
        assert explained.graph_count == 1 and not reasons, (part.__name__, reasons)
    dynamo.reset()


def test_training_is_perturbed_and_a_nominal_evaluation_is_not(built):
    """TrackingEnv.perturbed is what an evaluator asks (a deterministic wave may stop once no episode is
    alive; a perturbed one keeps stepping): training's env always, a nominal evaluation's never."""
    _, _, _, _, _, env, evaluator = built
    assert env.perturbed is True and evaluator.env.perturbed is False
