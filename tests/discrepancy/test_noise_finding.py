"""Issue 11, item 5: the noise as a finding, on logs that look like real ones (tests/discrepancy/log_like.py).

The noise is hidden in generated data the analysis receives only as rows: white noise, bias
instability made as flicker noise in the frequency domain (not the simulator's sum of Markov
processes), a rate random walk made by summing normal steps, over a slow thermal path with a
jittery, quantised temperature sensor. The fitted noise model must give them back within 25 % on
every channel, gyro and accelerometer, and the simulator's Allan deviation must come within 20 % of
the measured one at every octave from 1 s to a tenth of the record -- or, where the measured curve's
own 68 % interval is wider than that, within it (`excess_after`).
"""

from __future__ import annotations

import numpy as np
import pytest

from labrunner.discrepancy import Measurements, diagnose
from labrunner.discrepancy.allan import (
    TARGET,
    _design,
    _project,
    allan_curve,
    bases,
    model_curve,
    octave_taus,
    stretches,
)
from labrunner.domain import CHANNELS

from .log_like import _flicker, log_like

ACCEL = ("accel_x", "accel_y", "accel_z")


def _rel(got: float, hidden: float) -> float:
    return abs(got / hidden - 1.0)


def test_the_noise_is_a_finding_with_its_parameters_and_allan_gain(tmp_path):
    """A continuous 48 h log, three orientations (16 h each, no gap at the remounts)."""
    frame, truth = log_like(3, 48, continuous=True)
    result = diagnose(frame)
    assert result.verdict == "none"  # the noise never sets the verdict
    noise = next(f for f in result.findings if f.cause == "noise")
    assert noise.status == "noise" and set(noise.channels) == set(truth.white)
    p = noise.parameters
    for c in truth.white:
        assert _rel(p["white"][c], truth.white[c]) < 0.25, c
        assert _rel(p["bias_instability"][c], truth.bias_instability[c]) < 0.25, c
        assert _rel(p["rate_random_walk"][c], truth.rate_random_walk[c]) < 0.25, c
    fit = result.allan
    assert fit is not None
    # The records end at the remounts: octaves 1 s ... 4096 s, a tenth of 16 h at most.
    assert fit.measured.tau_s[0] == 1.0 and fit.measured.tau_s[-1] == 4096.0
    # Its gain: the simulated Allan deviation's mismatch, white-only before, fitted model after; the
    # target as written holds here at every octave, and so does the judgement against the interval.
    for c in noise.channels:
        assert noise.gain.heldout_rms_before[c] > 0.8
        assert fit.mismatch_after[c] <= TARGET, c
        assert fit.excess_after[c] == 0.0, c
        assert fit.excess_before[c] > 0.5, c  # white noise alone is far outside it
    # The measured curve's interval: within 1 % at 1 s, wider than 10 % at the top octave.
    low, high = fit.measured.low, fit.measured.high
    assert low is not None and high is not None
    assert np.all(low < fit.measured.adev) and np.all(fit.measured.adev < high)
    width = (high - low) / (2.0 * fit.measured.adev)
    assert np.all(width[0] < 0.01) and np.all(width[-1] > 0.1)
    allan = result.to_json()["allan"]  # the JSON reports both: the mismatch, and the interval it is judged against
    assert len(allan["measured_interval_68"]["accel_x"]) == fit.measured.tau_s.size
    assert allan["excess_after"] == {c: 0.0 for c in CHANNELS} and allan["mismatch_after"]["gyro_x"] <= TARGET
    # The extended model carries the fitted noise model, and the report draws the two curves.
    assert result.model.effects["bias_instability"].b["gyro_z"] == pytest.approx(p["bias_instability"]["gyro_z"])
    assert result.model.effects["bias_random_walk"].sigma_per_sqrt_s["accel_x"] == pytest.approx(
        p["rate_random_walk"]["accel_x"])
    from labrunner.discrepancy.report import write_report

    names = {path.name for path in write_report(result, tmp_path)}
    assert "allan_deviation.png" in names
    assert "bias instability B" in (tmp_path / "summary.md").read_text()


# Each channel its own mix; two channels without a random walk: the model goes only as far as the data asks.
MIXES = {
    "accel_x": (1.0e-4, 8e-5, 3e-6),
    "accel_y": (2.0e-4, 3e-5, 8e-6),
    "accel_z": (1.5e-4, 5e-5, 0.0),
    "gyro_x": (0.005, 2e-3, 4e-4),
    "gyro_y": (0.02, 6e-3, 0.0),
    "gyro_z": (0.01, 4e-3, 2e-4),
}


def test_each_channel_gets_its_own_noise_mix_back_through_dropouts():
    """A 72 h log, the sensor's temperature jittering by 0.05 degC, with logger dropouts (gaps of a few
    minutes inside an orientation, no power-on): the records end at the gaps too."""
    frame, truth = log_like(21, 72, continuous=True, jitter_c=0.05,
                            white={c: m[0] for c, m in MIXES.items()},
                            bias_instability={c: m[1] for c, m in MIXES.items()},
                            rate_random_walk={c: m[2] for c, m in MIXES.items()})
    keep = np.ones(len(frame), dtype=bool)
    for start in (20_000, 110_000, 200_000):  # three dropouts of 5 minutes
        keep[start:start + 300] = False
    frame = frame[keep].reset_index(drop=True)
    result = diagnose(frame)
    fit = result.allan
    assert fit is not None
    assert len(stretches(Measurements.from_frame(frame))) == 6  # 3 orientations + 3 dropouts
    for c, (white, instability, walk) in MIXES.items():
        assert _rel(fit.white[c], white) < 0.25, c
        assert _rel(fit.bias_instability[c], instability) < 0.25, c
        if walk > 0:
            assert _rel(fit.rate_random_walk[c], walk) < 0.25, c
        else:  # no walk hidden: what is fitted stays a small part of the top octave's Allan variance
            top = fit.measured.tau_s[-1]
            assert fit.rate_random_walk[c] ** 2 * top / 3.0 < 0.1 * fit.measured.adev[-1, CHANNELS.index(c)] ** 2, c
        assert fit.excess_after[c] == 0.0, c
    assert max(fit.mismatch_after.values()) <= TARGET + 0.05


def test_the_basis_predicts_a_foreign_noise_after_the_fit():
    """What the deterministic fit leaves of white noise, flicker and a random walk made by this test's
    own generator (not the simulator's) is what `bases` predicts, averaged over draws, at every octave
    to 1024 s -- on the accelerometers, whose baseline is fitted per orientation, too (the basis
    capped at the noise's own Allan variance, and records running across remounts, put the measured
    curve 15-20 % above the hidden noise at 256-2048 s)."""
    frame, _ = log_like(4, 24, continuous=True)
    meas = Measurements.from_frame(frame)
    parts = stretches(meas)
    taus = octave_taus(meas.row_dt_s, max(p.stop - p.start for p in parts) * meas.row_dt_s)
    taus = taus[taus <= 1024.0]
    basis = bases(meas, parts, taus)
    n = meas.t_s.size
    params = {"white": (1.5e-4, 0.0, 0.0), "flicker": (0.0, 5e-5, 0.0), "walk": (0.0, 0.0, 4e-6),
              "all": (1.5e-4, 5e-5, 4e-6)}
    rng = np.random.default_rng(77)
    draws = 6
    for triad, name in ((0, "accel"), (1, "gyro")):
        design = _design(meas, triad)
        design = design / np.sqrt(np.maximum(np.einsum("np,np->p", design, design), 1e-300))
        inverse = np.linalg.pinv(design.T @ design, rcond=1e-10, hermitian=True)
        for label, (w, b, k) in params.items():
            got = np.zeros(taus.size)
            for _ in range(draws):
                noise = np.column_stack([rng.standard_normal(n) * w * np.sqrt(0.5) + _flicker(rng, n, b)
                                         + np.cumsum(rng.standard_normal(n)) * k for _ in range(3)])
                got += np.mean(allan_curve(_project(noise, design, inverse), parts, meas.row_dt_s, taus).adev ** 2,
                               axis=1)
            predicted = basis[triad] @ np.array([w, b, k]) ** 2
            ratio = np.sqrt(got / draws / predicted)
            assert np.all(np.abs(ratio - 1.0) < 0.08), (name, label, np.round(ratio, 3))


def test_records_end_at_gaps_power_ons_and_remounts():
    frame, _ = log_like(8, 6, continuous=True)  # 6 h, an orientation every 2 h, run labels without power-ons
    frame = frame.drop(index=range(1000, 1010)).reset_index(drop=True)  # a 10 s dropout
    frame = frame.drop(index=range(1100, 1110)).reset_index(drop=True)  # and another 100 rows later
    meas = Measurements.from_frame(frame)
    parts = stretches(meas)
    o = meas.orientation
    starts = [p.start for p in parts]
    assert parts[0] == slice(0, 1000)  # up to the first dropout
    assert 1000 not in starts and 1100 in starts  # the 100 rows between the dropouts are too few for a record
    assert all(o[p.start] == o[p.stop - 1] for p in parts)  # one orientation each
    assert {int(i) for i in np.flatnonzero(np.diff(o)) + 1} <= set(starts)
    assert all(p.stop - p.start >= 256 for p in parts)
    assert len(np.unique(meas.run)) == 1  # no power-on among them: the records end at the remounts anyway


def test_a_top_octave_miss_is_the_measured_curves_own_scatter():
    """The worst log of bench_noise's seeds (10; 48 h): the fitted model misses the measured Allan deviation
    of accel_z by 40 % at 4096 s. The curve of the noise hidden in the log, seen through the same fit (the
    simulator's noise model at the hidden parameters on `bases`), shows whose miss it is: the measured curve
    lies 39 % below it there, the fitted model within the target of it at every octave on every channel. (Over
    24 such logs, 144 channels: the fitted model within 20 % of the hidden curve at every octave on all of
    them; the measured curve off it by a log-sd of 0.14 at 4096 s, where Greenhall's interval is +-0.12.)"""
    frame, truth = log_like(10, 48, continuous=True)
    fit = diagnose(frame).allan
    assert fit is not None
    meas = Measurements.from_frame(frame)
    taus = fit.measured.tau_s
    hidden = np.array([[truth.white[c], truth.bias_instability[c], truth.rate_random_walk[c]] for c in CHANNELS])
    true_curve = model_curve(hidden, bases(meas, stretches(meas), taus), taus).adev
    after_vs_measured = fit.after.adev / fit.measured.adev - 1.0
    missed = np.argwhere(np.abs(after_vs_measured) > TARGET)
    assert missed.size, "the miss this test is about is gone: update the docstring and bench figures"
    for j, i in missed:
        assert abs(fit.measured.adev[j, i] / true_curve[j, i] - 1.0) > TARGET, (taus[j], CHANNELS[i])
    assert np.all(np.abs(fit.after.adev / true_curve - 1.0) <= TARGET)


def test_the_allan_plot_draws_the_measured_interval_and_both_simulated_curves(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.collections import PolyCollection

    from labrunner.discrepancy.report import allan_figure

    frame, _ = log_like(8, 12, continuous=True)
    result = diagnose(frame)
    fit = result.allan
    assert fit is not None and fit.measured.low is not None and fit.measured.high is not None
    fig = allan_figure(result)
    for i, ax in enumerate(fig.axes[:6]):
        bands = [c for c in ax.collections if isinstance(c, PolyCollection)]
        assert len(bands) == 1, CHANNELS[i]
        scale = 1000.0 if CHANNELS[i].startswith("accel") else 1.0
        ys = bands[0].get_paths()[0].vertices[:, 1]
        # The band spans the interval: its lowest and highest points are the interval's.
        assert ys.min() == pytest.approx(fit.measured.low[:, i].min() * scale, rel=1e-9)
        assert ys.max() == pytest.approx(fit.measured.high[:, i].max() * scale, rel=1e-9)
        labels = [line.get_label() for line in ax.get_lines()]
        assert labels == ["measured residual", "simulator before (white only)", "simulator after (fitted noise model)"]
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert "measured, 68 % interval (Greenhall EDF)" in legend
