"""ONNX export of the policy with BeyondMimic-style metadata (what a deployment stack needs)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from bmimic.runs import atomic_write


def policy_metadata(env) -> dict[str, str]:
    """Joint names, PD gains, default pose, action scale and observation layout, as strings."""
    robot = env.robot

    def csv(x) -> str:
        return ",".join(f"{float(v):.6g}" for v in np.asarray(x).reshape(-1))

    obs_layout = []
    obs = env.get_observations()
    for name, fn, params in zip(env.policy_terms.names, env.policy_terms.funcs, env.policy_terms.params):
        obs_layout.append({"name": name, "dim": int(fn(env, **params).shape[-1])})
    body_names = [robot.body_names[int(i) - 1] for i in robot.tracked_body_ids]
    return {
        "joint_names": ",".join(robot.joint_names),
        "joint_stiffness": csv(robot.kp),
        "joint_damping": csv(robot.kd),
        "default_joint_pos": csv(robot.default_joint_pos),
        "action_scale": csv(robot.action_scale),
        "anchor_body_name": robot.body_names[int(robot.anchor_body_id) - 1],
        "body_names": ",".join(body_names),
        "observation_names": ",".join(x["name"] for x in obs_layout),
        "observation_layout": json.dumps(obs_layout),
        "policy_obs_dim": str(int(obs["policy"].shape[-1])),
        "control_dt_s": f"{env.step_dt:.6g}",
    }


def export_onnx(policy, env, path: str | os.PathLike) -> Path:
    """Write `policy` (an rsl-rl MLPModel) to an ONNX file with metadata, atomically."""
    import onnx
    import torch

    path = Path(path)
    model = policy.as_onnx(verbose=False)
    model.to("cpu").eval()

    def write(tmp: str) -> None:
        torch.onnx.export(
            model, model.get_dummy_inputs(), tmp, export_params=True, opset_version=18,
            input_names=model.input_names, output_names=model.output_names, dynamo=False,
        )
        proto = onnx.load(tmp)
        for key, value in policy_metadata(env).items():
            entry = proto.metadata_props.add()
            entry.key, entry.value = key, value
        onnx.save(proto, tmp)

    atomic_write(path, write)
    return path
