"""Robot models: the built-in robots by name (registry.py; their bodies in models/, their numbers in
conf/robot/), the generic MjSpec steps (spec.py), `RobotConfig` and `resolve_robot` (config.py).

The names below are imported on first use (PEP 562), as in bmimic.motion: the config schema
(`bmimic.robot.config`) imports without mujoco, so composing or printing a config (`--help`, `--cfg
job`, `bmimic-launch list`) does not pay for it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from bmimic.cli.deferred import names_on_first_use

_SOURCES = {
    "ActuatorClassConfig": "bmimic.robot.config",
    "RobotConfig": "bmimic.robot.config",
    "RobotInfo": "bmimic.robot.config",
    "RobotModelError": "bmimic.robot.config",
    "resolve_robot": "bmimic.robot.config",
    "G1_BODY_NAMES": "bmimic.robot.models.g1",
    "G1_JOINT_NAMES": "bmimic.robot.models.g1",
    "G1_SIM_OPTIONS": "bmimic.robot.models.g1",
    "build_spec": "bmimic.robot.registry",
    "load_mjmodel": "bmimic.robot.registry",
    "load_user_spec": "bmimic.robot.registry",
    "robot_config": "bmimic.robot.registry",
    "robot_names": "bmimic.robot.registry",
    "RobotModel": "bmimic.robot.spec",
    "SimOptions": "bmimic.robot.spec",
}

__all__ = [
    "ActuatorClassConfig",
    "G1_BODY_NAMES",
    "G1_JOINT_NAMES",
    "G1_SIM_OPTIONS",
    "RobotConfig",
    "RobotInfo",
    "RobotModel",
    "RobotModelError",
    "SimOptions",
    "build_spec",
    "load_mjmodel",
    "load_user_spec",
    "resolve_robot",
    "robot_config",
    "robot_names",
]

if TYPE_CHECKING:
    from bmimic.robot.config import (
        ActuatorClassConfig,
        RobotConfig,
        RobotInfo,
        RobotModelError,
        resolve_robot,
    )
    from bmimic.robot.models.g1 import G1_BODY_NAMES, G1_JOINT_NAMES, G1_SIM_OPTIONS
    from bmimic.robot.registry import build_spec, load_mjmodel, load_user_spec, robot_config, robot_names
    from bmimic.robot.spec import RobotModel, SimOptions

__getattr__ = names_on_first_use(__name__, _SOURCES, globals())
