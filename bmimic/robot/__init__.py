"""The Unitree G1 robot model: MjSpec builder (g1.py; the generic MjSpec steps in spec.py),
`load_mjmodel`, `RobotConfig` and `resolve_robot`.

The names below are imported on first use (PEP 562), as in bmimic.motion: the config schema
(`bmimic.robot.config`) imports without mujoco, so composing or printing a config (`--help`, `--cfg
job`, `bmimic-launch list`) does not pay for it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from bmimic.deferred import names_on_first_use

_SOURCES = {
    "ActuatorClassConfig": "bmimic.robot.config",
    "RobotConfig": "bmimic.robot.config",
    "RobotInfo": "bmimic.robot.config",
    "RobotModelError": "bmimic.robot.config",
    "resolve_robot": "bmimic.robot.config",
    "G1_BODY_NAMES": "bmimic.robot.g1",
    "G1_JOINT_NAMES": "bmimic.robot.g1",
    "G1_SIM_OPTIONS": "bmimic.robot.g1",
    "build_g1_spec": "bmimic.robot.g1",
    "configure_spec": "bmimic.robot.g1",
    "load_mjmodel": "bmimic.robot.g1",
    "SimOptions": "bmimic.robot.spec",
}

__all__ = [
    "ActuatorClassConfig",
    "G1_BODY_NAMES",
    "G1_JOINT_NAMES",
    "G1_SIM_OPTIONS",
    "RobotConfig",
    "RobotInfo",
    "RobotModelError",
    "SimOptions",
    "build_g1_spec",
    "configure_spec",
    "load_mjmodel",
    "resolve_robot",
]

if TYPE_CHECKING:
    from bmimic.robot.config import (
        ActuatorClassConfig,
        RobotConfig,
        RobotInfo,
        RobotModelError,
        resolve_robot,
    )
    from bmimic.robot.g1 import (
        G1_BODY_NAMES,
        G1_JOINT_NAMES,
        G1_SIM_OPTIONS,
        build_g1_spec,
        configure_spec,
        load_mjmodel,
    )
    from bmimic.robot.spec import SimOptions

__getattr__ = names_on_first_use(__name__, _SOURCES, globals())
