"""Reference motions: the `Motion` container, npz I/O, CSV conversion and the built-in motions.

The names below are imported on first use (PEP 562), so that the mujoco-free modules of this package
(`bmimic.motion.math`, `bmimic.motion.segments`) import without mujoco: sim2sim reads its quaternion
helpers from `bmimic.motion.math` and must choose MuJoCo's GL backend before mujoco is imported, and a
submodule imported with the package would make `python -m bmimic.motion.convert` warn under runpy.
"""

from bmimic.cli.startup import leave_working_directory

leave_working_directory(__name__)  # first: `python -m bmimic.motion.convert` runs this before convert

from typing import TYPE_CHECKING

from bmimic.cli.deferred import names_on_first_use

_SOURCES = {
    "BUILTIN_MOTIONS": "bmimic.motion.builtin",
    "generate_builtin": "bmimic.motion.builtin",
    "DataConfig": "bmimic.motion.config",
    "MotionConfig": "bmimic.motion.config",
    "lafan_clip_path": "bmimic.motion.config",
    "load_motion": "bmimic.motion.config",
    "Motion": "bmimic.motion.motion",
    "MotionDataError": "bmimic.motion.motion",
    "Segment": "bmimic.motion.motion",
    "convert_csv": "bmimic.motion.convert",
}

__all__ = [
    "BUILTIN_MOTIONS",
    "DataConfig",
    "Motion",
    "MotionConfig",
    "MotionDataError",
    "Segment",
    "convert_csv",
    "generate_builtin",
    "lafan_clip_path",
    "load_motion",
]

if TYPE_CHECKING:
    from bmimic.motion.builtin import BUILTIN_MOTIONS, generate_builtin
    from bmimic.motion.config import DataConfig, MotionConfig, lafan_clip_path, load_motion
    from bmimic.motion.convert import convert_csv
    from bmimic.motion.motion import Motion, MotionDataError, Segment

__getattr__ = names_on_first_use(__name__, _SOURCES, globals())
