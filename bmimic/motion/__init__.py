"""Reference motions: the `Motion` container, npz I/O, CSV conversion and the built-in motions."""

from bmimic.motion.builtin import BUILTIN_MOTIONS, generate_builtin
from bmimic.motion.config import DataConfig, MotionConfig, lafan_clip_path, load_motion
from bmimic.motion.motion import Motion, MotionDataError, Segment

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


def __getattr__(name: str):
    # Imported on first use: were bmimic.motion.convert imported with the package, `python -m
    # bmimic.motion.convert` would find it in sys.modules already and runpy would warn.
    if name == "convert_csv":
        from bmimic.motion.convert import convert_csv

        return convert_csv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
