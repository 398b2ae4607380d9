"""The paper's figures from a fit: files, axes, the data drawn, and skipping instead of failing."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.collections import PolyCollection

from labrunner.calibration import FitOptions, fit_campaign
from labrunner.calibration import figures as figures_mod
from labrunner.calibration.figures import write_figures
from labrunner.calibration.figures_fit import heldout_error_figure, term_curve, thermal_figure
from labrunner.calibration.figures_static import allan_curves, allan_figure, static_norm_figure, static_samples
from labrunner.calibration.headline import headline
from labrunner.calibration.outputs import write_outputs

from calib_campaigns import make_campaign

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
EXPECTED = {
    "thermal_accel_bias.png", "thermal_accel_scale.png", "thermal_gyro_bias.png", "thermal_gyro_scale.png",
    "heldout_error_accel.png", "heldout_error_gyro.png", "static_norm_accel.png", "static_norm_gyro.png",
    "allan_deviation.png",
}


@pytest.fixture(scope="module")
def campaign():
    return make_campaign(seed=51, temperatures_c=(-20.0, 0.0, 20.0, 40.0, 55.0), average_s=1.0)


@pytest.fixture(scope="module")
def result(campaign):
    return fit_campaign(campaign, FitOptions(splits=("random", "between_temperatures")), provenance={"source": "t"})


def _labelled(ax) -> bool:
    return bool(ax.get_xlabel()) and bool(ax.get_ylabel())


def test_a_fit_writes_every_figure_as_a_png(result, tmp_path):
    names = write_outputs(result, tmp_path)
    assert EXPECTED <= set(names)
    for name in EXPECTED:
        data = (tmp_path / name).read_bytes()
        assert data[:8] == PNG_MAGIC and len(data) > 20_000, name  # a drawn figure, not an empty canvas
    summary = (tmp_path / "summary.md").read_text()
    assert "## Figures" in summary and "`allan_deviation.png`" in summary
    assert "not drawn: `ins_position_error.png (paper Fig. 14)`" in summary  # said, not silently missing


def test_thermal_figure_draws_the_step_estimates_and_the_polynomial(result):
    fig = thermal_figure(result, "accel", "bias")
    axes = fig.axes
    assert "vs temperature" in fig.get_suptitle() and "mg" in fig.get_suptitle()
    main = axes[::2]  # (value, residual) per row
    assert all(ax.get_ylabel().endswith("(mg)") for ax in main)
    assert axes[-2].get_xlabel() == "IMU temperature (°C)" and all(ax.get_title() for ax in main)
    tp = result.polynomial.accel
    cals = result.models.six_position["accel"]
    for i, ax in enumerate(main):
        line = ax.lines[0]  # the polynomial
        t = np.asarray(line.get_xdata())
        np.testing.assert_allclose(line.get_ydata(), tp.bias_at(t)[:, i] * 1e3, rtol=1e-9, atol=1e-12)
        points = ax.lines[1]  # the errorbar's markers: the six-position estimate per step
        np.testing.assert_allclose(points.get_xdata(), [c.temp_c for c in cals])
        np.testing.assert_allclose(points.get_ydata(), [c.bias[i] * 1e3 for c in cals])
        assert any(isinstance(c, PolyCollection) for c in ax.collections), "the ±1σ band is drawn"
    # The band is the polynomial's uncertainty from the coefficient covariance: positive, and no wider
    # than a bias step estimate's own uncertainty times a few.
    _, sd = term_curve(tp, 0, "bias", np.array([c.temp_c for c in cals]))
    assert np.all(sd > 0) and np.all(sd < 5 * np.array([c.bias_std[0] for c in cals]))


def test_scale_figure_is_in_ppm_of_the_diagonal(result):
    fig = thermal_figure(result, "gyro", "scale")
    ax = fig.axes[2]  # y row
    assert ax.get_ylabel() == "scale-factor error y (ppm)"
    tp = result.polynomial.gyro
    t = np.asarray(ax.lines[0].get_xdata())
    np.testing.assert_allclose(ax.lines[0].get_ydata(), tp.scale_at(t)[:, 1, 1] * 1e6, rtol=1e-9)


def test_heldout_error_figure_shows_the_evaluation_numbers(result):
    fig = heldout_error_figure(result, "accel")
    ran = [s for s in result.evaluation if not s.skipped]
    assert len(fig.axes) == len(ran)
    for ax, split in zip(fig.axes, ran):
        assert ax.get_ylabel() == "RMS error (mg)" and ax.get_yscale() == "log" and split.name in ax.get_title()
        heights = [p.get_height() for p in ax.patches]
        expected = np.concatenate([split.samples[m].rms[:3] * 1e3 for m in split.samples])
        np.testing.assert_allclose(heights, expected)
    assert fig.axes[-1].get_xlabel()
    h = headline(result)
    g = h.gains["accel"]
    title = fig.get_suptitle()
    assert f"{g.raw_rms * 1e3:.3g}" in title and h.exported in title and h.split.name in title


def test_static_norm_figure_draws_the_norms_of_static_samples(result):
    samples = static_samples(result)
    assert samples.n_records == 5 * 6 * 2  # two rests per rate schedule, six orientations, five temperatures
    fig = static_norm_figure(samples, "accel")
    ax = fig.axes[0]
    assert _labelled(ax) and "expected" in fig.get_suptitle()
    raw = ax.lines[0]
    np.testing.assert_allclose(raw.get_ydata(), np.linalg.norm(samples.values["raw"][:, :3], axis=1))
    # Compensation brings the norm to 1 g: the compensated mean is far closer than the raw one.
    comp = np.asarray(ax.lines[1].get_ydata())
    assert abs(comp.mean() - 1) < 0.1 * abs(np.asarray(raw.get_ydata()).mean() - 1)


def test_allan_deviation_of_white_noise_falls_with_slope_minus_half(result):
    curves = allan_curves(result)
    assert curves.adev.shape == (curves.taus_s.size, 6) and curves.taus_s.size >= 3
    # The simulated noise is white at these averaging times: adev * sqrt(tau) stays near N.
    n = curves.adev * np.sqrt(curves.taus_s)[:, None]
    assert np.all(np.abs(n[:3] / n[0] - 1) < 0.35)
    fig = allan_figure(curves)
    for ax in fig.axes:
        assert ax.get_xscale() == "log" and ax.get_yscale() == "log" and _labelled(ax)
        labels = [ln.get_label() for ln in ax.lines]
        assert "slope −1/2 (white noise)" in labels and "slope +1/2 (random walk)" in labels
    np.testing.assert_allclose(fig.axes[1].lines[0].get_ydata(), curves.adev[:, 3])
    assert "white noise" in fig.get_suptitle()


def test_figures_the_data_cannot_support_are_skipped_with_a_reason(campaign, tmp_path):
    no_eval = fit_campaign(campaign, FitOptions(evaluate=False, rbf_variants=("hybrid",)))
    no_eval.samples = None  # a FitResult built without its figure rows
    report = write_figures(no_eval, tmp_path)
    assert "thermal_accel_bias.png" in report.written
    assert report.skipped["heldout_error_accel.png"] == "no evaluation ran (--no-eval)"
    assert "rows are not at hand" in report.skipped["static_norm_gyro.png"]
    assert "rows are not at hand" in report.skipped["allan_deviation.png"]
    rotating = campaign[campaign.table_rate_dps.abs() > 1.0]  # no record at rest
    res = fit_campaign(rotating, FitOptions(evaluate=False, rbf_variants=(), rbf_export=""))
    report = write_figures(res, tmp_path / "rotating")
    assert report.skipped["static_norm_accel.png"] == "no static records (table at rest) in the data"
    assert report.skipped["allan_deviation.png"] == "no static records (table at rest) in the data"


def test_a_figure_that_fails_to_draw_never_breaks_the_fit(result, tmp_path, monkeypatch):
    def broken(*_args: object) -> None:
        raise RuntimeError("no ink")

    monkeypatch.setattr(figures_mod, "thermal_figure", broken)
    names = write_outputs(result, tmp_path)
    assert "polynomial.json" in names and "heldout_error_accel.png" in names
    assert "thermal_accel_bias.png" not in names
    assert "not drawn: `thermal_accel_bias.png`: could not be drawn (RuntimeError: no ink)" in (
        tmp_path / "summary.md").read_text()


def test_figures_are_quick_on_a_small_fit(result, tmp_path):
    import time

    write_figures(result, tmp_path / "warm")  # imports and font cache
    t0 = time.perf_counter()
    report = write_figures(result, tmp_path / "timed")
    assert len(report.written) == len(EXPECTED)
    assert time.perf_counter() - t0 < 15.0  # ~2 s alone; generous for a shared 2-core CI machine


def test_log_axis_labels_are_plain_text_with_the_same_ticks(result):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    fig = allan_figure(allan_curves(result))
    ax = fig.axes[0]
    FigureCanvasAgg(fig).draw()
    mathtext = [t.get_text() for t in ax.xaxis.get_ticklabels() if t.get_text()]
    assert mathtext and all(s.startswith("$") for s in mathtext)  # matplotlib's own labels
    figures_mod.plain_log_labels(fig)
    FigureCanvasAgg(fig).draw()
    plain = [t.get_text() for t in ax.xaxis.get_ticklabels() if t.get_text()]
    assert plain == [figures_mod.plain_power(s) for s in mathtext] and not any("$" in s for s in plain)


def test_plain_power_writes_mathtext_powers_as_superscripts():
    assert figures_mod.plain_power(r"$\mathdefault{10^{-2}}$") == "10⁻²"
    assert figures_mod.plain_power(r"$\mathdefault{10^{1}}$") == "10¹"
    assert figures_mod.plain_power(r"$\mathdefault{2\times10^{-3}}$") == "2×10⁻³"
    assert figures_mod.plain_power("") == ""
    assert figures_mod.plain_power(r"$\mathdefault{0.5}$") == r"$\mathdefault{0.5}$"  # not a power: as it was


def test_titles_sit_at_the_top_of_their_axes(result, tmp_path):
    import matplotlib as mpl

    with mpl.rc_context(figures_mod._RC):
        fig = thermal_figure(result, "accel", "bias")
    assert all(not ax._autotitlepos for ax in fig.axes)  # no search for room above each axes when drawn
    assert fig.axes[0].title.get_position()[1] == 1.0
