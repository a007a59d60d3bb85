"""ONNX export of the policy with deployment metadata: the plain `obs -> actions` file and a
BeyondMimic-compatible file with the reference motion baked in.

Two files per checkpoint (`export_checkpoint_onnx`):

    policy_<it>.onnx          input `obs` [1, D]; output `actions` [1, J]
    motion_policy_<it>.onnx   inputs `obs` [1, D] and `time_step` [1, 1]; outputs `actions` and the
                              reference `joint_pos, joint_vel` [1, J], `body_pos_w, body_lin_vel_w,
                              body_ang_vel_w` [1, B, 3], `body_quat_w` [1, B, 4] (w, x, y, z) at the
                              time step clamped to [0, T-1], as the released BeyondMimic exporter writes
                              (whole_body_tracking utils/exporter.py), so its deployment controller can
                              play the motion from the file alone

Joints are in the order of `joint_names` (MuJoCo's depth-first order; an Isaac Lab-trained
BeyondMimic file uses Isaac Lab's breadth-first order, so a controller must map joints by name), the
B bodies in the order of `body_names` (the tracked bodies). Both files carry the same metadata, all
strings: BeyondMimic's keys (lists are comma-separated, as the released exporter writes them; numbers
are written with enough digits to round-trip a float64 where it writes 3 decimals) plus the keys
`bmimic.sim2sim` needs to rebuild the control loop without bmimic's training code (observation
layout with per-term sizes and functions, termination terms, physics and control periods, armature
and torque limits, motion frame rate, clips with their names and first frames, segments and time
bins) and `time_step_input`, how `time_step` picks a clip and a frame of a library.
`runs.schema.ONNX_METADATA_VERSION` names the set.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np

from bmimic.runs.folder import atomic_write, motion_policy_onnx_name, policy_onnx_name
from bmimic.runs.schema import ITERATION, ONNX_METADATA_VERSION

TIME_STEP_INPUT = ("frame index into the baked motion at motion_fps, one per control step; clip k (motion_clip_names[k]) "
                   "is frames motion_clip_starts[k] to motion_clip_starts[k+1]-1 (the last to motion_num_frames-1), "
                   "clamped to [0, motion_num_frames-1]; play one clip from its first frame to its last, never on "
                   "into the next. The policy sees no clip id or phase: only the reference at time_step "
                   "(observation terms motion_command, motion_anchor_pos_b, motion_anchor_ori_b)")
"""How a controller gives the motion policy its clip and time (metadata `time_step_input`)."""
MOTION_OUTPUTS = ("joint_pos", "joint_vel", "body_pos_w", "body_quat_w", "body_lin_vel_w", "body_ang_vel_w")
"""Reference outputs of the BeyondMimic-compatible file, after `actions`, in the released order."""


def csv(values) -> str:
    """Numbers as BeyondMimic's comma-separated metadata string, each written to round-trip exactly."""
    return ",".join(repr(float(v)) for v in np.asarray(values, dtype=np.float64).reshape(-1))


def _term_entries(terms, dims: list[int] | None = None) -> list[dict]:
    out = []
    for i, (name, cfg, params) in enumerate(zip(terms.names, terms.cfgs, terms.params)):
        entry = {"name": name, "func": str(cfg.func), "params": params}
        if dims is not None:
            entry["dim"] = dims[i]
        out.append(entry)
    return out


def policy_metadata(env, iteration: int | None = None, run_path: str = "") -> dict[str, str]:
    """Everything a deployment stack or `bmimic.sim2sim` needs to run the policy, as strings."""
    robot = env.robot
    sim = env.sim.cfg
    names = list(robot.body_names)  # MuJoCo body ids start at 1 (0 is the world)
    body_names = [names[int(i) - 1] for i in robot.tracked_body_ids]
    obs = env.get_observations()
    policy_terms, termination_terms = env.observations.groups["policy"], env.terminations.terms
    dims = env.observations.dims(env, "policy")
    terminations = [t for t, c in zip(_term_entries(termination_terms), termination_terms.cfgs) if not c.time_out]
    motion, layout = env.reference.motion, env.layout
    return {
        # BeyondMimic's keys (whole_body_tracking utils/exporter.py attach_onnx_metadata).
        "run_path": run_path,
        "joint_names": ",".join(robot.joint_names),
        "joint_stiffness": csv(robot.kp),
        "joint_damping": csv(robot.kd),
        "default_joint_pos": csv(robot.default_joint_pos),
        "command_names": "motion",
        "observation_names": ",".join(policy_terms.names),
        "observation_history_lengths": ",".join("1" for _ in policy_terms.names),
        "action_scale": csv(robot.action_scale),
        "anchor_body_name": names[int(robot.anchor_body_id) - 1],
        "body_names": ",".join(body_names),
        # bmimic's keys.
        "bmimic_metadata_version": ONNX_METADATA_VERSION,
        ITERATION: "" if iteration is None else str(int(iteration)),
        "observation_layout": json.dumps(_term_entries(policy_terms, dims)),
        "policy_obs_dim": str(int(obs["policy"].shape[-1])),
        "terminations": json.dumps(terminations),
        "root_body_name": names[0],
        "end_effector_body_names": ",".join(names[int(i) - 1] for i in robot.end_effector_body_ids),
        "joint_armature": csv(robot.armature),
        "joint_effort_limit": csv(robot.effort_limit),
        "control_dt_s": repr(float(env.step_dt)),
        "physics_dt_s": repr(float(sim.timestep_s)),
        "decimation": str(int(sim.decimation)),
        "sim_integrator": str(sim.integrator),
        "sim_solver": str(sim.solver),
        "sim_cone": str(sim.cone),
        "sim_iterations": str(int(sim.iterations)),
        "sim_ls_iterations": str(int(sim.ls_iterations)),
        "sim_max_abs_qvel": repr(float(sim.max_abs_qvel)),  # beyond these a world is broken (a failure)
        "sim_max_root_distance_m": repr(float(sim.max_root_distance_m)),
        "motion_fps": repr(float(motion.fps)),
        "motion_num_frames": str(int(motion.num_frames)),
        "motion_clip_starts": ",".join(str(int(s)) for s in np.asarray(motion.clip_starts).reshape(-1)),
        # JSON, not a comma list: a clip is named after its file, which may hold a comma
        "motion_clip_names": json.dumps(list(getattr(layout, "clip_names", ()))),
        "time_step_input": TIME_STEP_INPUT,
        "motion_segments": json.dumps([s._asdict() for s in motion.segments]),
        "bin_layout": layout.kind,  # "time" (bin_size_s wide) or "released" (BeyondMimic's B = T // 50 + 1)
        # the released layout has no fixed width: its mean bin length, for the record
        "bin_size_s": repr(float(getattr(layout, "bin_size_seconds", layout.duration_s / layout.num_bins))),
    }


def _motion_policy_module(policy, env):
    """The actor plus the tracked bodies' reference arrays, as BeyondMimic's exporter builds it."""
    import torch

    class MotionPolicy(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.actor = policy.as_onnx(verbose=False)
            ref = env.reference
            arrays = (ref.joint_pos, ref.joint_vel, ref.body_pos, ref.body_quat, ref.body_lin_vel, ref.body_ang_vel)
            for name, value in zip(MOTION_OUTPUTS, arrays):
                self.register_buffer(name, value.detach().to("cpu", torch.float32).clone())
            self.last_frame = ref.num_frames - 1

        def forward(self, obs: torch.Tensor, time_step: torch.Tensor):
            t = torch.clamp(time_step.long().squeeze(-1), 0, self.last_frame)
            return (self.actor(obs), *(getattr(self, name)[t] for name in MOTION_OUTPUTS))

    return MotionPolicy().to("cpu").eval()


def _write_onnx(model, inputs: tuple, input_names: list[str], output_names: list[str], metadata: dict[str, str],
                path: Path, opset: int) -> Path:
    import onnx
    import torch

    def write(tmp: str) -> None:
        # The TorchScript exporter on purpose (fixed shapes, opset 11 like the released files); its
        # deprecation notice is not for the user.
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.onnx.export(model, inputs, tmp, export_params=True, opset_version=opset, input_names=input_names,
                              output_names=output_names, dynamo=False)
        proto = onnx.load(tmp)
        for key, value in metadata.items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(proto, tmp)

    atomic_write(path, write)
    return path


def export_onnx(policy, env, path: str | os.PathLike, iteration: int | None = None, run_path: str = "") -> Path:
    """Write `policy` (an rsl-rl MLPModel) as `obs -> actions` to an ONNX file with metadata, atomically."""
    model = policy.as_onnx(verbose=False)
    model.to("cpu").eval()
    return _write_onnx(model, model.get_dummy_inputs(), model.input_names, model.output_names,
                       policy_metadata(env, iteration, run_path), Path(path), opset=18)


def export_motion_onnx(policy, env, path: str | os.PathLike, iteration: int | None = None,
                       run_path: str = "") -> Path:
    """Write the BeyondMimic-compatible file: `(obs, time_step) -> (actions, reference at time_step)`."""
    import torch

    model = _motion_policy_module(policy, env)
    inputs = (torch.zeros(1, model.actor.input_size), torch.zeros(1, 1))
    metadata = {**policy_metadata(env, iteration, run_path), "motion_baked_in": "true"}
    # Opset 11 and a fixed batch of 1, as the released exporter writes them.
    return _write_onnx(model, inputs, ["obs", "time_step"], ["actions", *MOTION_OUTPUTS], metadata, Path(path),
                       opset=11)


def export_checkpoint_onnx(policy, env, checkpoint_dir: str | os.PathLike, iteration: int) -> list[Path]:
    """Both files of one checkpoint, named after its iteration, in `checkpoint_dir` (a run's checkpoints/)."""
    checkpoint_dir = Path(checkpoint_dir)
    run_path = checkpoint_dir.resolve().parent.name
    return [
        export_onnx(policy, env, checkpoint_dir / policy_onnx_name(iteration), iteration, run_path),
        export_motion_onnx(policy, env, checkpoint_dir / motion_policy_onnx_name(iteration), iteration, run_path),
    ]
