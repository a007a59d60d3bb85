"""Robots by name: conf/robot/<name>.yaml holds a robot's numbers, bmimic/robot/models/<name>.py its body
(bmimic.robot.models). Nothing here names a particular robot."""

from __future__ import annotations

import re
from importlib import import_module
from pathlib import Path
from typing import cast

import mujoco

from bmimic.robot.config import RobotConfig, RobotModelError
from bmimic.robot.spec import RobotModel, compile_spec, configure_robot_spec, missing_mesh_files, parse_mjcf

DEFAULT_ROBOT = "g1"
"""The robot of conf/train.yaml's defaults, for callers with no config (converting a CSV, tests)."""


def robot_names() -> list[str]:
    """The built-in robots: a module in bmimic.robot.models and a conf/robot/<name>.yaml each."""
    from bmimic import CONF_DIR

    models = Path(__file__).resolve().parent / "models"
    return sorted(p.stem for p in (CONF_DIR / "robot").glob("*.yaml") if (models / f"{p.stem}.py").is_file())


def robot_model(name: str) -> RobotModel:
    """The body of built-in robot `name`."""
    if not re.fullmatch(r"[a-z][a-z0-9_]*", name or "") or name not in robot_names():
        raise RobotModelError(f"robot.name: unknown robot {name!r}; built-in robots: {robot_names()}")
    return cast(RobotModel, import_module(f"bmimic.robot.models.{name}").ROBOT)


def robot_config(name: str = DEFAULT_ROBOT) -> RobotConfig:
    """conf/robot/<name>.yaml as a RobotConfig (what `robot=<name>` composes)."""
    from omegaconf import OmegaConf

    from bmimic import CONF_DIR

    robot_model(name)  # a known robot, or one line that lists them
    values = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "robot" / f"{name}.yaml"))
    assert isinstance(values, dict)
    values.pop("defaults", None)
    return cast(RobotConfig, OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(RobotConfig), values)))


def build_spec(cfg: RobotConfig) -> mujoco.MjSpec:
    """The built-in robot `cfg.name` on a floor as an MjSpec (not compiled), configured by `cfg`."""
    return robot_model(cfg.name).build(cfg)


def load_user_spec(mjcf_path: str | Path, cfg: RobotConfig) -> mujoco.MjSpec:
    """A user's MJCF of robot `cfg.name` (e.g. with meshes), checked and configured like the built-in model."""
    model = robot_model(cfg.name)
    path = Path(mjcf_path).expanduser().resolve()
    spec = parse_mjcf(path, "robot.mjcf_path")
    missing = missing_mesh_files(spec, path)
    if missing:
        raise RobotModelError(
            f"robot.mjcf_path: {path} references {len(missing)} missing mesh files (first: {missing[0]}); "
            f"put the model's assets next to it or leave robot.mjcf_path unset to use the built-in {cfg.name}")
    try:
        configure_robot_spec(spec, cfg, model.joint_names, model.what, model.sim_options)
    except RobotModelError as exc:
        raise RobotModelError(f"robot.mjcf_path: {path}: {exc}") from None
    return spec


def load_mjmodel(name: str | None = None, mjcf_path: str | Path | None = None,
                 cfg: RobotConfig | None = None) -> mujoco.MjModel:
    """The compiled robot on its floor: the built-in model, or the user's `mjcf_path` if given.

    `cfg` defaults to conf/robot/<name>.yaml (`name` defaults to cfg.name, else DEFAULT_ROBOT); a
    `mjcf_path` of None takes cfg.mjcf_path.
    """
    if cfg is None:
        cfg = robot_config(name or DEFAULT_ROBOT)
    elif name is not None and name != cfg.name:
        raise RobotModelError(f"robot.name: {name!r} asked for, the robot config is {cfg.name!r}")
    mjcf_path = mjcf_path if mjcf_path is not None else cfg.mjcf_path
    if mjcf_path:
        return compile_spec(load_user_spec(mjcf_path, cfg), f"robot.mjcf_path: {mjcf_path}")
    return compile_spec(build_spec(cfg), f"built-in robot {cfg.name!r}")
