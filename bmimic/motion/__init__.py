"""Reference motions: the `Motion` container, npz I/O, CSV conversion and the built-in motions."""

from bmimic.motion.builtin import BUILTIN_MOTIONS, generate_builtin
from bmimic.motion.config import MotionConfig, load_motion
from bmimic.motion.convert import convert_csv
from bmimic.motion.motion import Motion, MotionDataError, Segment

__all__ = [
    "BUILTIN_MOTIONS",
    "Motion",
    "MotionConfig",
    "MotionDataError",
    "Segment",
    "convert_csv",
    "generate_builtin",
    "load_motion",
]
