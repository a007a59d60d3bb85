"""analysis.plots directly: every figure function draws a known number of lines, bars, cells and dots
from a tiny tidy table, and writes a non-empty PNG (analysis.files.save_figure, atomically)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib import colormaps
from matplotlib.collections import PathCollection, QuadMesh
from matplotlib.patches import Rectangle

from analysis import curve_plots, palette, plots
from analysis.files import save_figure

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png(fig, tmp_path, name: str) -> bytes:
    path = save_figure(tmp_path / name, fig)
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC) and len(data) > 1000
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp file left behind
    return data


def _dots(ax) -> int:
    """Points drawn as scatter markers."""
    return sum(len(c.get_offsets()) for c in ax.collections if isinstance(c, PathCollection))


def _bins(n: int = 4) -> pd.DataFrame:
    """metrics.bin_table's shape: two segments, the last bin horizon-truncated."""
    return pd.DataFrame({"bin": range(n), "bin_start_s": np.arange(n, dtype=float),
                         "bin_end_s": np.arange(1, n + 1, dtype=float),
                         "segment": ["walk"] * (n // 2) + ["jump"] * (n - n // 2),
                         "horizon_truncated": [False] * (n - 1) + [True]})


def test_arm_colors_are_stable_and_distinct():
    colors = plots.arm_colors(["b", "a", "c", "a"])
    assert list(colors) == ["a", "b", "c"] and len(set(colors.values())) == 3
    assert plots.arm_colors(["c", "a", "b"]) == colors


STUDY_ARMS = ["sampler=adaptive", "sampler=uniform",
              *(f"sampler.gamma={g},sampler=adaptive" for g in ("0.5", "0.7", "0.8", "0.95", "1.0")),
              *(f"sampler.K={k},sampler=adaptive" for k in (1, 3, 9)),
              *(f"sampler.bin_size_seconds={b},sampler=adaptive" for b in ("0.25", "0.5", "2.0", "4.0"))]


def test_a_study_of_many_arms_gets_distinct_colours_by_family():
    colors = palette.arm_colors(STUDY_ARMS)
    assert len(STUDY_ARMS) > palette.MANY_ARMS and len(set(colors.values())) == len(STUDY_ARMS)
    # the plain sampler choices stand apart: the reference black, uniform grey
    assert colors["sampler=adaptive"] == palette.SINGLE_COLORS[0]
    assert colors["sampler=uniform"] == palette.SINGLE_COLORS[1]

    def darkness(arm):
        return -sum(colors[arm][:3])

    # one knob's levels share a hue and darken with the knob's value (numeric order: 9 after 3, 4.0 after 2.0)
    assert darkness("sampler.K=1,sampler=adaptive") < darkness("sampler.K=3,sampler=adaptive") < darkness(
        "sampler.K=9,sampler=adaptive")
    assert darkness("sampler.bin_size_seconds=2.0,sampler=adaptive") < darkness(
        "sampler.bin_size_seconds=4.0,sampler=adaptive")
    hue = {arm: int(np.argmax(colors[arm][:3])) for arm in STUDY_ARMS if "gamma" in arm}
    assert len(set(hue.values())) == 1
    # few arms keep tab10 in sorted order (the committed reports' colours)
    assert palette.arm_colors(STUDY_ARMS[:3]) == {a: colormaps["tab10"](i) for i, a in enumerate(sorted(STUDY_ARMS[:3]))}


def test_many_arms_put_one_legend_beside_the_last_panel():
    its = np.arange(4)
    curves = pd.concat([pd.DataFrame({"arm": arm, "iteration": its, "point": its * 0.1, "ci_low": its * 0.1,
                                      "ci_high": its * 0.1, "metric": m}) for arm in STUDY_ARMS
                        for m in ("nominal", "robust")])
    fig = curve_plots.plot_whole_clip_success(curves, curves.rename(columns={"point": "value"}).assign(run_dir="r"))
    legends = [ax.get_legend() for ax in fig.axes]
    assert legends[0] is None and legends[-1] is not None
    assert len(legends[-1].get_texts()) == len(STUDY_ARMS)
    assert fig.get_size_inches()[0] > 4.6 * 2  # widened once to hold it
    few = plots.plot_learning_curve(curves[curves["arm"].isin(STUDY_ARMS[:2]) & (curves["metric"] == "nominal")])
    assert few.axes[0].get_legend() is not None and tuple(few.get_size_inches()) == plots.FIGSIZE


def test_learning_curve_one_line_per_arm_and_per_seed(tmp_path):
    its = np.arange(5)
    curves = pd.concat([pd.DataFrame({"arm": arm, "iteration": its, "point": its * k, "ci_low": its * k - 1,
                                      "ci_high": its * k + 1}) for arm, k in (("uniform", 1.0), ("adaptive", 2.0))])
    per_seed = pd.concat([pd.DataFrame({"arm": "uniform", "run_dir": f"s{s}", "iteration": its, "value": its + s})
                          for s in range(3)])
    fig = plots.plot_learning_curve(curves, "reward", per_seed=per_seed, title="t")
    ax = fig.axes[0]
    thick = [line for line in ax.get_lines() if line.get_linewidth() > 1.0]
    assert sorted(line.get_label() for line in thick) == ["adaptive", "uniform"]
    assert len(ax.get_lines()) == 2 + 3  # arms, then seeds
    assert len(ax.collections) == 2  # one band per arm
    adaptive = next(line for line in thick if line.get_label() == "adaptive")
    np.testing.assert_allclose(adaptive.get_ydata(), its * 2.0)
    assert ax.get_ylabel() == "reward"
    _png(fig, tmp_path, "curve.png")


def test_bin_heatmap_has_one_cell_per_iteration_and_bin(tmp_path):
    df = pd.DataFrame([(it, b, it / 10 + b / 100) for it in (0, 10, 30) for b in range(4)],
                      columns=["iteration", "bin", "failure_rate"])
    fig = plots.plot_bin_heatmap(df, bins=_bins())
    mesh = next(c for c in fig.axes[0].collections if isinstance(c, QuadMesh))
    values = np.asarray(mesh.get_array()).reshape(3, 4)
    np.testing.assert_allclose(values, df.pivot(index="iteration", columns="bin", values="failure_rate").to_numpy())
    assert len(fig.axes) == 2  # the heatmap and its colour bar
    _png(fig, tmp_path, "heatmap.png")


def test_bin_heatmaps_one_panel_per_arm_on_one_scale(tmp_path):
    df = pd.DataFrame([(arm, it, b, k * (b + 1) / 8) for arm, k in (("a", 1.0), ("b", 2.0)) for it in (0, 5)
                       for b in range(4)], columns=["arm", "iteration", "bin", "failure_rate"])
    fig = plots.plot_bin_heatmaps(df, bins=_bins())
    meshes = [next(c for c in ax.collections if isinstance(c, QuadMesh)) for ax in fig.axes[:2]]
    assert [ax.get_title() for ax in fig.axes[:2]] == ["a", "b"]
    assert {m.get_clim() for m in meshes} == {(0.0, 1.0)}  # shared scale up to the largest value
    _png(fig, tmp_path, "heatmaps.png")


def test_final_bin_failure_lines_bands_and_seed_dots(tmp_path):
    final = pd.DataFrame([(arm, b, 0.1 * b, 0.0, 0.2 * b, "0.1;0.2;0.3") for arm in ("a", "b") for b in range(4)],
                         columns=["arm", "bin", "point", "ci_low", "ci_high", "per_seed"])
    fig = plots.plot_final_bin_failure(final, bins=_bins())
    ax = fig.axes[0]
    assert sorted(line.get_label() for line in ax.get_lines() if not line.get_label().startswith("_")) == ["a", "b"]
    assert _dots(ax) == 2 * 4 * 3  # every seed of every bin of every arm
    assert ax.get_ylim()[0] == 0
    _png(fig, tmp_path, "final.png")


def test_final_bin_failure_draws_each_arms_seed_dots_in_one_scatter():
    """One collection of seed dots per arm, bin after bin, censored seeds left out, shifted per arm (a
    scatter call per bin and arm took the 8,018-bin library report over 20 minutes)."""
    cells = ["0.1;0.2", ">5;0.3", ""]
    final = pd.DataFrame([(arm, b, 0.1, 0.0, 0.2, cell) for arm in ("b", "a") for b, cell in enumerate(cells)],
                         columns=["arm", "bin", "point", "ci_low", "ci_high", "per_seed"])
    ax = plots.plot_final_bin_failure(final, colors={"a": "C0", "b": "C1"}).axes[0]
    scatters = [c for c in ax.collections if isinstance(c, PathCollection)]
    assert len(scatters) == 2
    for scatter, jitter in zip(scatters, (-0.06, 0.06), strict=True):  # arms in sorted order: a, then b
        np.testing.assert_allclose(scatter.get_offsets(), [[jitter, 0.1], [jitter, 0.2], [1 + jitter, 0.3]])


def test_mastery_marks_unreached_bins_and_censored_seeds(tmp_path):
    mastery = pd.DataFrame({"arm": ["a"] * 3, "bin": [0, 1, 2], "mastery_iteration": [10.0, 20.0, np.nan],
                            "follow_up": [50.0, 50.0, 50.0]})
    per_seed = pd.DataFrame({"arm": "a", "bin": [0, 0, 1, 2], "mastered": [True, True, True, False],
                             "iteration": [10, 12, 20, np.nan], "last_iteration": [50, 50, 50, 50]})
    fig = plots.plot_mastery(mastery, per_seed, bins=_bins(3), threshold=0.1)
    ax = fig.axes[0]
    scatters = [c for c in ax.collections if isinstance(c, PathCollection)]
    # the open triangle of the unreached bin, 3 seeds that got there, 1 censored seed
    assert sorted(len(c.get_offsets()) for c in scatters) == [1, 1, 3]
    assert "0.1" in ax.get_title()
    _png(fig, tmp_path, "mastery.png")


def test_speedup_bars_and_bound_labels(tmp_path):
    speed = pd.DataFrame({"arm": ["fast", "fast", "slow", "slow"], "measure": ["iteration", "env_steps"] * 2,
                          "ratio": [2.0, 2.0, 0.5, np.nan], "ci_low": [1.5, np.nan, 0.4, np.nan],
                          "ci_high": [2.5, np.nan, 0.6, np.nan],
                          "status": ["estimate", "lower_bound", "estimate", "not_estimable"]})
    per_seed = pd.DataFrame({"arm": "fast", "measure": "iteration", "value": [1.8, 2.2]})
    fig = plots.plot_speedup(speed, per_seed)
    ax = fig.axes[0]
    bars = [p for p in ax.patches if isinstance(p, Rectangle) and p.get_width() > 0]
    assert sorted(round(b.get_height(), 6) for b in bars) == [0.0, 0.5, 2.0, 2.0]  # n/e is drawn empty
    assert sorted(t.get_text() for t in ax.texts) == ["n/e", "≥"]
    assert _dots(ax) == 2
    assert ax.get_ylim()[1] == pytest.approx(2.5 * 1.15)  # room above the highest whisker
    _png(fig, tmp_path, "speedup.png")


def test_sensitivity_one_line_per_series_with_reference(tmp_path):
    sens = pd.DataFrame([("sampler.gamma", g, series, f"{series}{g}", "final_failure", g / 2, g / 2 - 0.1, g / 2 + 0.1)
                         for series in ("K=1", "K=3") for g in (0.5, 0.9)],
                        columns=["key", "value", "series", "arm", "metric", "point", "ci_low", "ci_high"])
    per_seed = pd.DataFrame({"arm": ["K=10.5", "K=10.5", "K=30.9"], "value": [0.2, 0.3, 0.4]})
    fig = plots.plot_sensitivity(sens, "final_failure", reference={"uniform (baseline)": 0.6}, per_seed=per_seed)
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert sorted(labels) == ["K=1", "K=3", "uniform (baseline)"]
    assert [line.get_ydata()[0] for line in ax.get_lines() if line.get_linestyle() == "--"] == [0.6]
    assert ax.get_xlabel() == "sampler.gamma" and ax.get_ylabel() == "final overall failure"
    assert _dots(ax) == 3
    _png(fig, tmp_path, "sensitivity.png")


# ------------------------------------------------------------------------- a study the size of a real one
def _report_figures(study, tmp_path, monkeypatch) -> tuple[dict, str]:
    """Build the report of ``study``, keeping every figure it saves (name -> Figure) and its text."""
    from analysis import report, report_files
    from analysis.tables import ReportOptions

    figures = {}

    def keep(path, fig):
        figures[path.name] = fig
        return save_figure(path, fig)

    monkeypatch.setattr(report_files, "save_figure", keep)  # the report's file writer
    out = report.build_report([study], tmp_path / "report", ReportOptions(n_resamples=20))
    return figures, (out / "report.md").read_text()


def _tick_labels(axis) -> list:
    """The tick labels drawn on ``axis`` (in view, non-empty), after a draw."""
    lo, hi = sorted(axis.get_view_interval())
    return [t for t in axis.get_ticklabels() if t.get_visible() and t.get_text() and lo <= t.get_position()[
        0 if axis.axis_name == "x" else 1] <= hi]


def _check_ticks(fig, name: str) -> None:
    """Every bin and iteration axis: at least one label, integer values, no two labels overlapping."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig).draw()
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_label_text() not in ("bin", "iteration", "mastery iteration"):
                continue
            labels = _tick_labels(axis)
            assert labels, f"{name}: {axis.get_label_text()} axis has no tick label"
            values = [float(t.get_text().replace("−", "-")) for t in labels]
            assert all(v == int(v) for v in values), f"{name}: fractional ticks {values}"
            boxes = sorted((t.get_window_extent(renderer) for t in labels), key=lambda b: (b.x0, b.y0))
            for a, b in zip(boxes, boxes[1:], strict=False):
                assert not a.overlaps(b), f"{name}: tick labels {values} overlap on the {axis.axis_name} axis"


def _panels(fig) -> dict[str, QuadMesh]:
    return {ax.get_title(): next(c for c in ax.collections if isinstance(c, QuadMesh))
            for ax in fig.axes if ax.get_title()}


def test_a_200_bin_7_arm_study_has_readable_figures(tmp_path, monkeypatch):
    from tests.analysis.synthetic_runs import WIDE_ARMS, make_wide_study

    figures, md = _report_figures(make_wide_study(tmp_path, num_bins=200, last_iteration=30), tmp_path, monkeypatch)
    for name, fig in figures.items():
        _check_ticks(fig, name)
        fig.savefig(tmp_path / f"check_{name}", dpi=100)  # what a reader sees (the report's dpi)
    fail = _panels(figures["bin_failure_heatmap.png"])
    assert sorted(fail) == [f"sampler={a}" for a in sorted(WIDE_ARMS)]
    assert len({m.get_clim() for m in fail.values()}) == 1  # failure rates: one scale for every arm
    # Sampling: each panel on its own scale, so one arm's bright bin (0.9) leaves the others readable.
    samp = _panels(figures["sampling_distribution.png"])
    assert samp["sampler=beyondmimic"].get_clim() == (0.0, pytest.approx(0.9))
    for arm, mesh in samp.items():
        cells = np.asarray(mesh.get_array(), dtype=float)
        assert mesh.get_clim()[1] == pytest.approx(np.nanmax(cells)), arm
        if arm != "sampler=beyondmimic":
            assert mesh.get_clim()[1] < 0.2, arm
    # 7 panels in rows of at most 4; segment names above the top row only.
    heat = figures["bin_failure_heatmap.png"]
    assert {round(ax.get_position().y0, 2) for ax in heat.axes if ax.get_title()}.__len__() == 2
    assert "10 not estimable" in md and "not estimables" not in md and "10 lower bounds" in md


def test_a_smoke_study_gets_integer_iteration_ticks(tmp_path, monkeypatch):
    from tests.analysis.synthetic_runs import make_wide_study

    study = make_wide_study(tmp_path, num_bins=30, last_iteration=3, eval_every=100, never=0, name="smoke")
    figures, _ = _report_figures(study, tmp_path, monkeypatch)
    for name, fig in figures.items():
        _check_ticks(fig, name)
    heat = figures["bin_failure_heatmap.png"].axes[0]
    assert [t.get_text() for t in _tick_labels(heat.yaxis)] == ["0", "3"]  # the evaluated iterations
    assert heat.get_ylim()[0] == -0.5  # iteration 0's cell does not reach negative iterations
