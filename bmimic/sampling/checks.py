"""Range checks of sampler options and the error they raise. Each sampler's config schema states the
rules of its keys with these (its `check`, :mod:`bmimic.sampling.schemas`), run once when the config is
validated; a bad value gets a one-line message naming the key. Comparisons are written
`not (lo < x <= hi)` so that NaN fails them."""

from __future__ import annotations

import math
from typing import Any

from bmimic import BmimicError


class SamplerConfigError(BmimicError, ValueError):
    """A sampler option, or a sampler input that depends on one, is invalid."""


def fail(key: str, rule: str, value: Any) -> None:
    """Raise SamplerConfigError("sampler.<key> must be <rule>, got <value>")."""
    raise SamplerConfigError(f"sampler.{key} must be {rule}, got {value!r}")


def is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def check_fraction(key: str, x: Any, closed_below: bool = False) -> None:
    """x in (0, 1] (or [0, 1] with closed_below)."""
    ok = is_number(x) and (0.0 <= x <= 1.0 if closed_below else 0.0 < x <= 1.0)
    if not ok:
        fail(key, "in [0, 1]" if closed_below else "in (0, 1]", x)


def check_choice(key: str, x: Any, choices: tuple[str, ...]) -> None:
    if x not in choices:
        fail(key, f"one of {', '.join(choices)}", x)


def check_int_at_least(key: str, x: Any, low: int, high: int | None = None) -> None:
    """An integer >= low (and <= high, when given)."""
    if not (isinstance(x, int) and not isinstance(x, bool) and x >= low and (high is None or x <= high)):
        fail(key, f"an integer >= {low}" + (f" and <= {high}" if high is not None else ""), x)


def check_positive(key: str, x: Any) -> None:
    """A finite number > 0."""
    if not (is_number(x) and 0.0 < x < math.inf):
        fail(key, "a finite number > 0", x)


def check_nonnegative(key: str, x: Any) -> None:
    """A finite number >= 0."""
    if not (is_number(x) and 0.0 <= x < math.inf):
        fail(key, "a finite number >= 0", x)


__all__ = ["SamplerConfigError", "check_choice", "check_fraction", "check_int_at_least", "check_nonnegative",
           "check_positive", "fail",
           "is_number"]
