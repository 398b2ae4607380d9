"""The diagnosis report's plots: one figure-level legend outside the axes, and no figure drawn twice
when runs and orientations coincide one-to-one."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from labrunner.discrepancy import diagnose  # noqa: E402
from labrunner.discrepancy.report import (  # noqa: E402
    PLOTS,
    gain_figure,
    per_group_figure,
    runs_are_orientations,
    scatter_figure,
    write_report,
)

from .campaigns import DRAWS, campaign  # noqa: E402
from .test_hidden_effects import case_seed  # noqa: E402


def _diagnosis(power_cycle: str):
    seed = case_seed("report-plots")
    hidden = DRAWS["hysteresis"](np.random.default_rng(seed))
    frame, _ = campaign([hidden], "sims", seed, power_cycle=power_cycle)
    return diagnose(frame)


@pytest.fixture(scope="module")
def one_run_per_orientation():
    return _diagnosis("orientation")


@pytest.fixture(scope="module")
def one_run_per_temperature():
    return _diagnosis("temperature")


def test_one_to_one_runs_and_orientations_draw_one_figure(one_run_per_orientation, tmp_path):
    assert runs_are_orientations(one_run_per_orientation.residuals)
    names = {p.name for p in write_report(one_run_per_orientation, tmp_path)}
    assert "residual_by_run.png" in names and "residual_by_orientation.png" not in names
    assert not (tmp_path / "residual_by_orientation.png").exists()
    summary = (tmp_path / "summary.md").read_text()
    assert "`residual_by_run.png` stands for both run and orientation" in summary
    assert "residual_by_orientation.png" not in summary.split("## Plots")[1].split("stands for")[0]


def test_runs_across_orientations_draw_both_figures(one_run_per_temperature, tmp_path):
    assert not runs_are_orientations(one_run_per_temperature.residuals)
    names = {p.name for p in write_report(one_run_per_temperature, tmp_path)}
    assert {"residual_by_run.png", "residual_by_orientation.png"} <= names
    assert "stands for both" not in (tmp_path / "summary.md").read_text()


def _figures(diagnosis):
    table = diagnosis.residuals
    yield from (scatter_figure(table, column, label) for _, column, label, _ in PLOTS)
    yield per_group_figure(table, "run", "run (power-on)", with_orientation=True)
    yield per_group_figure(table, "orientation", "orientation (specific force)")
    yield gain_figure(diagnosis)


def test_every_figure_has_one_figure_legend_outside_the_axes(one_run_per_orientation):
    for fig in _figures(one_run_per_orientation):
        try:
            title = fig._suptitle.get_text() if fig._suptitle is not None else "?"
            assert len(fig.legends) == 1, title
            assert all(ax.get_legend() is None for ax in fig.axes), title
            fig.canvas.draw()
            box = fig.legends[0].get_window_extent()
            for ax in fig.axes:  # the legend sits over no panel
                assert not box.overlaps(ax.get_window_extent()), title
            labels = [t.get_text() for t in fig.legends[0].get_texts()]
            assert any("baseline" in t for t in labels) and any("extended" in t for t in labels), title
        finally:
            plt.close(fig)


def test_extended_model_is_a_thin_line_over_the_baseline_points(one_run_per_orientation):
    fig = scatter_figure(one_run_per_orientation.residuals, "t_on_s", "time since power-on (s)")
    try:
        for ax in fig.axes:
            (line,) = [ln for ln in ax.get_lines() if "extended" in ln.get_label()]
            assert line.get_linewidth() <= 1.5 and line.get_marker() in ("None", "", None)
            assert all(coll.get_zorder() < line.get_zorder() for coll in ax.collections)
    finally:
        plt.close(fig)
