"""Arm colours and legends that stay readable from two arms to a knob study's twenty-odd.

Up to MANY_ARMS arms every figure keeps tab10 in sorted order (the committed reports' colours). Beyond
it tab10 repeats colours, so arms are coloured by family instead: the arms that change the same keys of
the same sampler (one knob's levels) share a hue, in shades ordered by the knob's value; the plain sampler
choices (a study's reference and uniform) get black, grey and then tab10's colours. The legend then
moves beside the axes, which widen the figure, instead of covering the curves.
"""

from __future__ import annotations

import math

import numpy as np

from analysis.load import arm_items

MANY_ARMS = 10
"""Above this many arms a figure colours by family and puts its legend outside the axes."""

FAMILY_MAPS = ("Blues", "Oranges", "Greens", "Reds", "Purples", "YlOrBr", "RdPu", "GnBu")
"""Sequential colormaps of the families, in the order of the families' sorted keys (cycled)."""

SINGLE_COLORS = ((0.0, 0.0, 0.0, 1.0), (0.55, 0.55, 0.55, 1.0))
"""The first plain sampler arms (sorted: e.g. `sampler=adaptive`, `sampler=uniform`); tab10 after them."""


def _order_value(value: str) -> tuple[float, str]:
    try:
        number = float(value)
    except ValueError:
        return math.inf, value
    return (number, value) if math.isfinite(number) else (math.inf, value)


def arm_colors(arms) -> dict[str, tuple]:
    """A stable colour per arm (module docstring): tab10 in sorted order up to MANY_ARMS, else by family."""
    from matplotlib import colormaps

    arms = sorted({str(a) for a in arms})
    tab10 = colormaps["tab10"]
    if len(arms) <= MANY_ARMS:
        return {arm: tab10(i % 10) for i, arm in enumerate(arms)}
    families: dict[tuple, list[str]] = {}
    singles = []
    for arm in arms:
        items = arm_items(arm)
        knobs = tuple(sorted(k for k in items if k != "sampler"))
        if knobs:
            families.setdefault((items.get("sampler", ""), knobs), []).append(arm)
        else:
            singles.append(arm)
    out: dict[str, tuple] = {}
    for i, arm in enumerate(singles):
        out[arm] = SINGLE_COLORS[i] if i < len(SINGLE_COLORS) else tab10((i - len(SINGLE_COLORS)) % 10)
    for f, (key, members) in enumerate(sorted(families.items())):
        cmap = colormaps[FAMILY_MAPS[f % len(FAMILY_MAPS)]]
        knobs = key[1]
        members = sorted(members, key=lambda a: tuple(_order_value(arm_items(a)[k]) for k in knobs))
        shades = np.linspace(0.4, 0.95, len(members)) if len(members) > 1 else [0.7]
        out.update({arm: cmap(float(s)) for arm, s in zip(members, shades, strict=True)})
    return out


def place_legend(ax, fontsize: float = 7) -> None:
    """The axes' legend: inside (matplotlib's best place) up to MANY_ARMS entries; else once per figure,
    beside its last axes (the arms keep their colours across panels), with the figure widened to hold it."""
    handles, labels = ax.get_legend_handles_labels()
    if len(labels) <= MANY_ARMS:
        ax.legend(fontsize=fontsize)
        return
    fig = ax.figure
    target = fig.axes[-1]
    if target.get_legend() is not None:
        return
    width, height = fig.get_size_inches()
    longest = max(len(label) for label in labels)
    fig.set_size_inches(width + 0.6 + 0.055 * longest, max(height, 0.14 * len(labels) + 0.9))
    target.legend(handles, labels, fontsize=6, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False,
                  borderaxespad=0.0)


__all__ = ["FAMILY_MAPS", "MANY_ARMS", "SINGLE_COLORS", "arm_colors", "place_legend"]
