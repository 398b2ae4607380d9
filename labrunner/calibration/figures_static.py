"""Figures of static samples: the norms before and after compensation (paper Figs. 10-11) and the
Allan deviation per channel.

Both need samples, not record means: they use the bounded set of rows the fit gathered
(`FitResult.samples`, fit_rows.FigureRows). The norms are drawn from a decimated subset of every
static record's rows (the fit's own records: calibration data, not held out); the Allan deviation
from the longest static records at full rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from matplotlib.figure import Figure

from .compensation import compensate
from .figure_style import DISPLAY, TRIAD_TITLES, FigureSkipped, colour, fmt, headline, new_figure
from .fit import FitResult
from .fit_rows import FigureRows, allan_records
from .fit_rows import static_records as _static_records
from .headline import exported_name
from .rbf_model import RbfModel
from .thermal_poly import PolyModel
from .triads import AXES, TRIAD_SLICE


@dataclass
class StaticSamples:
    """Static rows (decimated) in time order, raw and compensated."""

    temp_c: np.ndarray  # (n,) IMU temperature
    values: dict[str, np.ndarray]  # model name ("raw" first) -> (n, 6)
    every: int  # decimation: every k-th static row
    n_records: int


def static_records(result: FitResult) -> np.ndarray:
    """Indices of the records with the table at rest."""
    return _static_records(result.records)


def _samples(result: FitResult) -> FigureRows:
    if result.samples is None:
        raise FigureSkipped("the fit's rows are not at hand (FitResult without its figure rows)")
    return result.samples


def static_samples(result: FitResult) -> StaticSamples:
    """The static rows the fit gathered (every k-th, at most fit_rows.MAX_NORM_POINTS), raw and compensated."""
    rows = _samples(result)
    if rows.n_static_records == 0:
        raise FigureSkipped("no static records (table at rest) in the data")
    a = rows.norm
    assert a is not None
    y = np.asarray(a["y"], dtype=float)
    temp = np.asarray(a["temp"], dtype=float)
    models: dict[str, PolyModel | RbfModel] = {"polynomial": result.polynomial}
    if result.rbf is not None:
        models[exported_name(result)] = result.rbf
    values = {"raw": y} | {name: compensate(m, y, temp).values for name, m in models.items()}
    return StaticSamples(temp_c=temp, values=values, every=rows.every, n_records=rows.n_static_records)


def static_norm_figure(samples: StaticSamples, triad: str) -> Figure:
    """|specific force| (should be 1 g) or |angular rate| (should be 0) of the static samples."""
    sl = TRIAD_SLICE[triad]
    expected = 1.0 if triad == "accel" else 0.0
    unit = "g" if triad == "accel" else "°/s"
    what = "specific force" if triad == "accel" else "angular rate"
    digits = 5 if triad == "accel" else 3  # around 1 g the compensation shows in the 3rd to 5th decimal
    fig, axes = new_figure(1, 1, (10, 5.2), right=0.85, top=0.7)
    ax = axes[0, 0]
    x = np.arange(samples.temp_c.size)
    means: dict[str, float] = {}
    for name, v in samples.values.items():
        norm = np.linalg.norm(v[:, sl], axis=1)
        means[name] = float(norm.mean())
        rms_err = float(np.sqrt(np.mean((norm - expected) ** 2)))
        # Later models drawn smaller on top: when two agree, both stay visible.
        size = {"raw": 3.0, "polynomial": 4.0}.get(name, 2.0)
        ax.plot(x, norm, linestyle="none", marker=".", ms=size, color=colour(name),
                label=f"{name}: mean {means[name]:.{digits}f} {unit}, RMS error {rms_err:.{digits}f} {unit}")
    ax.axhline(expected, color="black", lw=1, linestyle="--", label=f"expected: {expected:g} {unit}")
    ax.set_xlabel(f"static sample, in time order ({samples.n_records} records at rest"
                  + (f", every {samples.every}th sample)" if samples.every > 1 else ")"))
    ax.set_ylabel(f"|{what}| ({unit})")
    tax = ax.twinx()
    tax.plot(x, samples.temp_c, color="#bcbd22", lw=1, label="IMU temperature")
    tax.set_ylabel("IMU temperature (°C)", color="#8c8c00")
    ax.legend(fontsize=8, loc="upper left", markerscale=4)
    chain = ", ".join(f"{means[n]:.{digits}f} {unit} {n}" for n in samples.values)
    headline(fig, f"Static |{what}|, mean: {chain} ({expected:g} {unit} expected)")
    ax.set_title("the campaign's static records (calibration data, not held out)", fontsize=10)
    return fig


@dataclass
class AllanCurves:
    """Allan deviation per channel, averaged over the longest static records."""

    taus_s: np.ndarray  # (m,)
    adev: np.ndarray  # (m, 6) in model units (g, deg/s)
    n_records: int
    record_s: float  # duration of the shortest record used
    temps_c: np.ndarray  # IMU temperature of each record used

    def white_noise(self) -> np.ndarray:
        """(6,) white-noise coefficient N = adev(tau) sqrt(tau) at the shortest tau (units/sqrt(Hz))."""
        return self.adev[0] * np.sqrt(self.taus_s[0])


def allan_curves(result: FitResult) -> AllanCurves:
    import allantools  # imported here: only this figure needs it

    rows = _samples(result)
    recs = static_records(result)
    if recs.size == 0:
        raise FigureSkipped("no static records (table at rest) in the data")
    n = result.records.n_rows[recs]
    chosen = allan_records(result.records)
    if result.records.n_rows[chosen].min() < 8:
        raise FigureSkipped(f"the longest static record has {int(n.max())} samples; the Allan deviation needs 8")
    per_record: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # taus, avar (m, 6), terms (m, 6)
    for r in chosen:
        y = np.asarray(rows.allan[int(r)]["y"], dtype=float)
        rate = 1.0 / float(result.records.row_interval_s[r])
        cols = [allantools.oadev(y[:, j], rate=rate, data_type="freq", taus="octave") for j in range(6)]
        taus = np.asarray(cols[0][0], dtype=float)
        per_record.append((taus, np.column_stack([np.asarray(c[1]) ** 2 for c in cols]),
                           np.column_stack([np.asarray(c[3], dtype=float) for c in cols])))
    m = min(p[0].size for p in per_record)
    if m < 2:
        raise FigureSkipped("the static records are too short for two averaging times")
    taus = per_record[0][0][:m]
    # Average the Allan variance over records, weighted by the number of terms behind each estimate.
    weights = np.stack([p[2][:m] for p in per_record])
    avar = np.sum(np.stack([p[1][:m] for p in per_record]) * weights, axis=0) / np.sum(weights, axis=0)
    return AllanCurves(taus_s=taus, adev=np.sqrt(avar), n_records=int(chosen.size),
                       record_s=float(np.min(result.records.duration_s[chosen])),
                       temps_c=result.records.temp_c[chosen])


def allan_figure(curves: AllanCurves) -> Figure:
    """Allan deviation per channel, log-log, with the white-noise (−1/2) and random-walk (+1/2) slopes."""
    fig, axes = new_figure(1, 2, (11, 5.2), left=1.0, top=0.7, wspace=0.3)
    tau = curves.taus_s
    nwhite = curves.white_noise()
    for ax, triad in zip(axes[0], ("accel", "gyro")):
        factor, unit = DISPLAY[triad]
        sl = TRIAD_SLICE[triad]
        adev = curves.adev[:, sl] * factor
        for j, axis in enumerate(AXES):
            ax.loglog(tau, adev[:, j], marker="o", ms=3, label=f"{triad} {axis}: N = {fmt(nwhite[sl][j] * factor)} "
                      f"{unit}/√Hz")
        top = float(np.max(adev[0]))
        ax.loglog(tau, top * np.sqrt(tau[0] / tau), color="black", linestyle="--", lw=1,
                  label="slope −1/2 (white noise)")
        k = np.unravel_index(int(np.argmin(adev)), adev.shape)
        low, tau_low = float(adev[k]), float(tau[k[0]])
        upper = tau >= np.sqrt(tau[0] * tau[-1])  # a reference slope, kept out of the legend's corner
        ax.loglog(tau[upper], low * np.sqrt(tau[upper] / tau_low), color="black", linestyle=":", lw=1,
                  label="slope +1/2 (random walk)")
        ax.set_xlabel("averaging time τ (s)")
        ax.set_ylabel(f"Allan deviation ({unit})")
        ax.set_title(f"{TRIAD_TITLES[triad]} ({curves.temps_c.min():.0f} … {curves.temps_c.max():.0f} °C)",
                     fontsize=11)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8, loc="lower left")
    acc = float(np.median(nwhite[:3])) * DISPLAY["accel"][0]
    gyr = float(np.median(nwhite[3:]))
    headline(fig, f"Allan deviation, {curves.n_records} static record(s) of {curves.record_s:.0f} s: white noise "
                  f"{fmt(acc)} mg/√Hz (accel), {fmt(gyr)} °/s/√Hz = {fmt(gyr * 60)} °/√h (gyro)")
    return fig
