"""The Unitree G1 robot model: MjSpec builder (g1.py; the generic MjSpec steps in spec.py),
`load_mjmodel`, `RobotConfig` and `resolve_robot`."""

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
