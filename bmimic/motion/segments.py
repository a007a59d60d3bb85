"""The two types every motion module shares: `Segment` (a labelled time range of a motion, saved as
JSON in the npz) and `MotionDataError` (bad motion data, one line)."""

from __future__ import annotations

import json
from typing import NamedTuple, Sequence

from bmimic import BmimicError
from bmimic.runs import safe_read


class MotionDataError(BmimicError, ValueError):
    """Bad motion data or a motion that does not fit the robot model; the message is one line."""


class Segment(NamedTuple):
    """A labelled time range of a motion (used to name time bins in the analysis)."""

    name: str
    start_s: float
    end_s: float
    difficulty: str


def segments_to_json(segments: Sequence[Segment]) -> str:
    return json.dumps([s._asdict() for s in segments])


def segments_from_json(text: str) -> list[Segment]:
    try:
        items = safe_read.parse_json(text, "segments")
    except ValueError as err:
        raise MotionDataError(f"segments is not valid JSON ({err})") from None
    if not isinstance(items, list):
        raise MotionDataError("segments must be a JSON list of {name, start_s, end_s, difficulty}")
    out = []
    for k, i in enumerate(items):
        try:
            seg = Segment(str(i["name"]), float(i["start_s"]), float(i["end_s"]), str(i["difficulty"]))
        except (KeyError, TypeError, ValueError) as err:
            raise MotionDataError(f"segments entry {k} is malformed ({err!r}); expected "
                                  "{name, start_s, end_s, difficulty}") from None
        out.append(seg)
    return out
