"""The numpy control loop: one robot in native MuJoCo driven by the ONNX policy, its observations,
terminations and tracking errors, and one evaluation episode (optionally perturbed: `EpisodeHooks`,
which bmimic.sim2sim.perturb.Draw is). Worker processes: bmimic.sim2sim.workers."""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Callable, NamedTuple, Protocol

import numpy as np

from bmimic.motion.math import quat_to_matrix, rotation_angle
from bmimic.runs.schema import ERROR_COLUMNS, HORIZON_TRUNCATED, MPKPE_REL_MM, SMOOTHNESS_COLUMNS
from bmimic.sim2sim.spec import PolicySpec

if TYPE_CHECKING:
    from bmimic.motion.motion import Motion

ERROR_NAMES = ERROR_COLUMNS
"""Per-step tracking errors, named and ordered as the run schema's (bmimic.runs.schema.ERROR_COLUMNS)."""
REL_MPKPE = ERROR_NAMES.index(MPKPE_REL_MM)
SMOOTHNESS_NAMES = SMOOTHNESS_COLUMNS
"""The policy's per-step smoothness (bmimic.runs.schema.SMOOTHNESS_COLUMNS)."""
MEASURED = (*ERROR_NAMES, *SMOOTHNESS_NAMES)


# ============================================================================================ rollout
class Rollout:
    """One robot in native MuJoCo driven by the policy: reset to a reference frame, step, observe.

    Mirrors the evaluation environment's step: PD targets held for `decimation` physics steps,
    kinematics of the new state, terminations against the current reference frame, then the frame
    advances (stopping at the clip's last frame) and the observation is built from the new frame.
    Rotations are handled as matrices (MuJoCo's xmat, the reference's precomputed once), which gives
    the same quantities as the training code's quaternion formulas.
    """

    def __init__(self, mjm, spec: PolicySpec, ref: Motion, session=None) -> None:
        import mujoco

        self.m, self.d = mjm, mujoco.MjData(mjm)
        self.spec, self.ref, self.session = spec, ref, session
        jid = [mjm.joint(n).id for n in spec.joint_names]
        self.qadr = mjm.jnt_qposadr[jid].astype(np.int64)
        self.vadr = mjm.jnt_dofadr[jid].astype(np.int64)
        free = int(np.flatnonzero(mjm.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
        self.free_q, self.free_v = int(mjm.jnt_qposadr[free]), int(mjm.jnt_dofadr[free])
        self.body_ids = np.array([mjm.body(n).id for n in spec.body_names], dtype=np.int64)
        self.anchor = spec.body_names.index(spec.anchor_body)
        self.root = spec.body_names.index(spec.root_body)
        self.ee = np.array([spec.body_names.index(n) for n in spec.end_effector_bodies], dtype=np.int64)
        self.ref_mat = quat_to_matrix(ref.body_quat_w)  # [T, B, 3, 3]
        ends = np.append(ref.clip_starts[1:], ref.num_frames)
        self.clip_end = np.repeat(ends, np.diff(np.append(ref.clip_starts, ref.num_frames)))  # frame -> its clip's end
        self.actions = np.zeros(len(spec.joint_names))
        self.default_joint_pos = spec.default_joint_pos
        """The action offset and the joint observation's origin (a robust rollout offsets it)."""
        self.obs_noise: np.ndarray | None = None
        """[obs_dim] half-widths of uniform noise on the policy input, drawn from `rng` (None: none)."""
        self.rng: np.random.Generator | None = None
        self.frame = 0
        self.segment_end = spec.num_frames
        self._obs = np.zeros((1, spec.obs_dim), dtype=np.float32)
        self._time = np.zeros((1, 1), dtype=np.float32)
        self._bad = mujoco.mjtWarning.mjWARN_BADQACC
        self._terms = [(getattr(self, "_t_" + f), p) for _, f, p in spec.terminations]
        self._obs_fns = [getattr(self, "_o_" + t.func) for t in spec.obs_terms]
        self._error_fns = [getattr(self, "_e_" + name) for name in ERROR_NAMES]
        self._version = 0  # bumped by every change of the physics state
        self._cached: tuple = (None, None)

    # ---------------------------------------------------------------------------------- state
    def reference_qpos(self, frame: int) -> np.ndarray:
        """qpos of the reference pose at `frame` (root body pose + joint angles)."""
        r, f = self.ref, self._clamp(frame)
        qpos = self.m.qpos0.copy()
        qpos[self.free_q:self.free_q + 3] = r.body_pos_w[f, self.root]
        qpos[self.free_q + 3:self.free_q + 7] = r.body_quat_w[f, self.root]
        qpos[self.qadr] = r.joint_pos[f]
        return qpos

    def reset(self, frame: int) -> None:
        """Put the robot exactly at the reference state of `frame` (no noise), actions zero."""
        r, f = self.ref, self._clamp(frame)
        qvel = np.zeros(self.m.nv)
        qvel[self.free_v:self.free_v + 3] = r.body_lin_vel_w[f, self.root]
        # The free joint's angular velocity is in the body frame.
        qvel[self.free_v + 3:self.free_v + 6] = self.ref_mat[f, self.root].T @ r.body_ang_vel_w[f, self.root]
        qvel[self.vadr] = r.joint_vel[f]
        self.set_state(self.reference_qpos(f), qvel, f, np.zeros(len(self.spec.joint_names)))

    def set_state(self, qpos: np.ndarray, qvel: np.ndarray, frame: int, actions: np.ndarray) -> None:
        """Any state: qpos/qvel in this model's layout, the reference frame, the last action."""
        import mujoco

        mujoco.mj_resetData(self.m, self.d)
        self.d.qpos[:] = qpos
        self.d.qvel[:] = qvel
        self.frame = int(frame)
        self.segment_end = int(self.clip_end[self._clamp(frame)])
        self.actions = np.asarray(actions, dtype=np.float64).copy()
        mujoco.mj_forward(self.m, self.d)
        self.touch()

    def touch(self) -> None:
        """The physics state was changed from outside a step (a push): state() is computed anew."""
        self._version += 1

    def _clamp(self, frame: int) -> int:
        return min(max(int(frame), 0), self.spec.num_frames - 1)

    def state(self) -> dict:
        """Robot and reference quantities at the current physics state and reference frame (cached)."""
        key = (self._version, self.frame)
        if self._cached[0] == key:
            return self._cached[1]
        d, r, a = self.d, self.ref, self.anchor
        f = self._clamp(self.frame)
        pos = d.xpos[self.body_ids]
        mat = d.xmat[self.body_ids].reshape(-1, 3, 3)
        ref_pos, ref_mat = r.body_pos_w[f], self.ref_mat[f]
        # Anchor-centred, yaw-aligned, height-preserving targets (BeyondMimic): the yaw of
        # R_robot_anchor R_ref_anchor^T rotates the reference about the robot's anchor.
        m = mat[a] @ ref_mat[a].T
        yaw = math.atan2(m[1, 0], m[0, 0])
        c, s_ = math.cos(yaw), math.sin(yaw)
        rz = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        origin = np.array([pos[a, 0], pos[a, 1], ref_pos[a, 2]])
        state = {
            "joint_pos": d.qpos[self.qadr], "joint_vel": d.qvel[self.vadr],
            "root_lin_vel_w": d.qvel[self.free_v:self.free_v + 3],
            "root_ang_vel_b": d.qvel[self.free_v + 3:self.free_v + 6],
            "pos": pos, "mat": mat,
            "ref_joint_pos": r.joint_pos[f], "ref_joint_vel": r.joint_vel[f],
            "ref_pos": ref_pos, "ref_mat": ref_mat,
            "rel_pos": origin + (ref_pos - ref_pos[a]) @ rz.T,
            "rel_mat": rz @ ref_mat,
        }
        self._cached = (key, state)
        return state

    # ---------------------------------------------------------------------------------- observations
    def observation(self) -> np.ndarray:
        """[1, obs_dim] float32 policy input at the current state and frame."""
        s = self.state()
        i = 0
        for fn, term in zip(self._obs_fns, self.spec.obs_terms):
            self._obs[0, i:i + term.dim] = fn(s)
            i += term.dim
        if self.obs_noise is not None and self.rng is not None:  # both set together (perturb.apply)
            self._obs[0] += (2.0 * self.rng.random(self.spec.obs_dim) - 1.0) * self.obs_noise
        return self._obs

    def _o_motion_command(self, s):
        return np.concatenate((s["ref_joint_pos"], s["ref_joint_vel"]))

    def _o_motion_anchor_pos_b(self, s):
        a = self.anchor
        return s["mat"][a].T @ (s["ref_pos"][a] - s["pos"][a])

    def _o_motion_anchor_ori_b(self, s):
        a = self.anchor  # first two columns of R_anchor^T R_ref_anchor, row by row
        return (s["mat"][a].T @ s["ref_mat"][a])[:, :2].reshape(-1)

    def _o_robot_body_pos_b(self, s):
        a = self.anchor
        return ((s["pos"] - s["pos"][a]) @ s["mat"][a]).reshape(-1)

    def _o_robot_body_ori_b(self, s):
        return np.einsum("ji,bjk->bik", s["mat"][self.anchor], s["mat"])[:, :, :2].reshape(-1)

    def _o_base_lin_vel(self, s):
        return s["mat"][self.root].T @ s["root_lin_vel_w"]  # the root body's frame is the free joint's

    def _o_base_ang_vel(self, s):
        return s["root_ang_vel_b"]

    def _o_joint_pos_rel(self, s):
        return s["joint_pos"] - self.default_joint_pos

    def _o_joint_vel_rel(self, s):
        return s["joint_vel"]

    def _o_last_action(self, s):
        return self.actions

    # ---------------------------------------------------------------------------------- terminations
    def _t_bad_anchor_pos_z_only(self, s, threshold_m: float) -> bool:
        return abs(s["ref_pos"][self.anchor, 2] - s["pos"][self.anchor, 2]) > threshold_m

    def _t_bad_anchor_ori(self, s, threshold: float) -> bool:
        # z of gravity (0, 0, -1) in the anchor frame is -R[2, 2]: the difference of cos(tilt).
        return abs(s["ref_mat"][self.anchor, 2, 2] - s["mat"][self.anchor, 2, 2]) > threshold

    def _t_bad_motion_body_pos_z_only(self, s, threshold_m: float) -> bool:
        err = np.abs(s["rel_pos"][self.ee, 2] - s["pos"][self.ee, 2])
        return bool((err > threshold_m).any())

    def terminated(self) -> bool:
        """Any termination term at the current state and frame."""
        s = self.state()
        return any(fn(s, **params) for fn, params in self._terms)

    # ---------------------------------------------------------------------------------- errors
    def errors(self) -> np.ndarray:
        """The ERROR_NAMES at the current state and frame, each by its `_e_<name>` (the evaluation env's
        definitions, bmimic.envs.measures.ERROR_TERMS, with rotations as matrices)."""
        s = self.state()
        return np.array([float(fn(s)) for fn in self._error_fns])

    def _e_mpkpe_mm(self, s):
        return 1000.0 * np.linalg.norm(s["ref_pos"] - s["pos"], axis=-1).mean()

    def _e_mpkpe_rel_mm(self, s):
        a = self.anchor
        return 1000.0 * np.linalg.norm((s["ref_pos"] - s["ref_pos"][a]) - (s["pos"] - s["pos"][a]), axis=-1).mean()

    def _e_anchor_ori_err_rad(self, s):
        return rotation_angle(s["ref_mat"][self.anchor], s["mat"][self.anchor])

    def _e_body_ori_err_rad(self, s):
        return rotation_angle(s["rel_mat"], s["mat"]).mean()

    def _e_joint_pos_err_rad(self, s):
        return np.abs(s["ref_joint_pos"] - s["joint_pos"]).mean()

    def _e_joint_vel_err_radps(self, s):
        return np.abs(s["ref_joint_vel"] - s["joint_vel"]).mean()

    def _e_ee_pos_err_mm(self, s):
        return 1000.0 * np.linalg.norm(s["rel_pos"][self.ee] - s["pos"][self.ee], axis=-1).mean()

    def smoothness(self, last_actions: np.ndarray, last_joint_vel: np.ndarray) -> np.ndarray:
        """The SMOOTHNESS_NAMES of the step just taken from `last_actions` and `last_joint_vel`."""
        joint_vel = self.d.qvel[self.vadr]
        return np.array((float(np.square(self.actions - last_actions).sum()),
                         float(np.abs(joint_vel - last_joint_vel).mean() / self.spec.control_dt_s)))

    # ---------------------------------------------------------------------------------- stepping
    def policy_action(self) -> np.ndarray:
        """The deterministic action for the current observation and reference frame."""
        self._time[0, 0] = self.frame
        return self.session.run(["actions"], {"obs": self.observation(), "time_step": self._time})[0][0]

    def physics(self, actions: np.ndarray) -> bool:
        """Hold the PD targets of `actions` for one control step; False if the world broke: the actions
        were not finite, MuJoCo had to reset the state, or the state is non-finite or beyond training's
        bounds (|qvel| above sim_max_abs_qvel, the root beyond sim_max_root_distance_m), as the
        training simulator's broken worlds."""
        import mujoco

        self.actions = np.asarray(actions, dtype=np.float64).copy()
        if not np.isfinite(self.actions).all():
            return False  # MuJoCo would zero a non-finite ctrl and carry on; the policy itself broke
        self.d.ctrl[:] = self.default_joint_pos + self.spec.action_scale * self.actions
        bad = self.d.warning[self._bad].number
        for _ in range(self.spec.decimation):
            mujoco.mj_step(self.m, self.d)
        mujoco.mj_kinematics(self.m, self.d)  # body poses of the new state
        self._version += 1
        qvel, root = self.d.qvel, self.d.qpos[self.free_q:self.free_q + 3]
        return (self.d.warning[self._bad].number == bad and bool(np.isfinite(self.d.qpos).all())
                and bool(np.isfinite(qvel).all()) and float(np.abs(qvel).max(initial=0.0)) <= self.spec.max_abs_qvel
                and float(np.linalg.norm(root)) <= self.spec.max_root_distance_m)

    def advance(self) -> bool:
        """Next reference frame (held at the clip's last one); True once that last frame is reached."""
        self.frame = min(self.frame + 1, self.segment_end - 1)
        return self.frame >= self.segment_end - 1


class EpisodeHooks(Protocol):
    """What perturbs an episode (bmimic.sim2sim.perturb.Draw): called before the reset, after it, after
    each step's terminations and errors, and at the end (even on an error)."""

    def start(self, rollout: Rollout) -> None: ...

    def after_reset(self, rollout: Rollout) -> None: ...

    def after_step(self, rollout: Rollout) -> None: ...

    def finish(self, rollout: Rollout) -> None: ...


class Episode(NamedTuple):
    """One evaluation episode: its tidy row and the errors of each step where they were measured."""

    row: dict
    """bmimic.training.evaluator.EPISODE_COLUMNS, `error_failed`, the mean of each MEASURED entry over
    the alive steps, `broken` (= `diverged`: the world broke, a failure) and `wall_s`."""
    frames: np.ndarray
    """[steps] the reference frame each step was judged at."""
    errors: np.ndarray
    """[steps, len(MEASURED)] the errors and smoothness of each step."""


def run_episode(rollout: Rollout, start_frame: int, horizon_steps: int, max_mpkpe_rel_mm: float | None = None,
                on_step: Callable[[Rollout, bool], None] | None = None, draw: EpisodeHooks | None = None) -> Episode:
    """One evaluation episode, accounted exactly as bmimic.training.evaluator.Evaluator.run_episodes does.

    Each step is judged at the frame the reference stood at when it began (terminations; the step's
    errors, measured after the reference advanced, are summed at that frame). The episode ends at a
    termination (failed, charged at that frame), when the reference reaches its clip's last frame
    (`end_frame` is then that frame) or at the horizon; `horizon_truncated` when the clip ends before the
    horizon. With `max_mpkpe_rel_mm`, an episode that did not terminate but whose mean anchor-relative
    MPKPE exceeds it fails, charged at its worst step's frame (the first, on ties). A step after which
    the world broke (Rollout.physics: MuJoCo reset it, or its state or the actions left their bounds)
    ends the episode as a failure at that step's frame (`broken`, and `diverged` for the tables of
    earlier versions), and its errors (of a state that no longer exists) are not counted.

    `draw` (EpisodeHooks, e.g. bmimic.sim2sim.perturb.Draw): the episode's perturbations, applied before
    the reset, after it, after each step's terminations and errors (pushes), and taken off at the end.
    """
    if draw is None:
        return _run_episode(rollout, start_frame, horizon_steps, max_mpkpe_rel_mm, on_step, None)
    draw.start(rollout)
    try:
        return _run_episode(rollout, start_frame, horizon_steps, max_mpkpe_rel_mm, on_step, draw)
    finally:
        draw.finish(rollout)


def _run_episode(rollout: Rollout, start_frame: int, horizon_steps: int, max_mpkpe_rel_mm: float | None,
                 on_step: Callable[[Rollout, bool], None] | None, draw: EpisodeHooks | None) -> Episode:
    rollout.reset(start_frame)
    if draw is not None:
        draw.after_reset(rollout)
    start = rollout.frame
    truncated = rollout.segment_end - 1 - start < horizon_steps
    if on_step is not None:
        on_step(rollout, False)
    frames: list[int] = []
    errors: list[np.ndarray] = []
    terminated = diverged = False
    end_frame = start
    t0 = time.perf_counter()
    for _ in range(horizon_steps):
        frame = end_frame = rollout.frame
        last_actions, last_joint_vel = rollout.actions.copy(), rollout.d.qvel[rollout.vadr].copy()
        action = rollout.policy_action()
        if not rollout.physics(action):
            diverged = True
            break
        stop = rollout.terminated()
        clip_end = rollout.advance()
        frames.append(frame)
        errors.append(np.concatenate((rollout.errors(), rollout.smoothness(last_actions, last_joint_vel))))
        if on_step is not None:
            on_step(rollout, stop)
        if stop:
            terminated = True
            break
        if clip_end:
            end_frame = rollout.frame  # tracked up to the clip's last frame
            break
        if draw is not None:
            draw.after_step(rollout)  # pushes come after the step's terminations (the env's order)
    err = np.asarray(errors, dtype=np.float64).reshape(len(frames), len(MEASURED))
    means = err.sum(axis=0) / max(len(frames), 1)
    error_failed = bool(max_mpkpe_rel_mm is not None and not (terminated or diverged)
                        and means[REL_MPKPE] > max_mpkpe_rel_mm)
    if terminated or diverged:
        failure_frame = end_frame
    elif error_failed:
        failure_frame = frames[int(np.argmax(err[:, REL_MPKPE]))]
    else:
        failure_frame = -1
    row = {
        "start_frame": int(start), "end_frame": int(end_frame), "failed": terminated or diverged or error_failed,
        "failure_frame": int(failure_frame), "terminated": terminated, "error_failed": error_failed,
        "steps": len(frames), HORIZON_TRUNCATED: bool(truncated), **dict(zip(MEASURED, means.tolist())),
        "broken": diverged, "diverged": diverged, "wall_s": time.perf_counter() - t0,
    }
    return Episode(row, np.asarray(frames, dtype=np.int64), err)
