"""Figures drawn from the fitted models alone: the thermal polynomials (paper Figs. 3-6) and the
held-out errors the evaluation computed (Figs. 7-8)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .figure_style import DISPLAY, TRIAD_TITLES, FigureSkipped, colour, fmt, headline, new_figure
from .fit import FitResult
from .headline import headline as fit_headline
from .thermal_poly import TriadPoly
from .triads import AXES, TRIAD_SLICE

TERMS = {"bias": "bias", "scale": "scale-factor error"}
PPM = 1e6


def term_units(triad: str, term: str) -> tuple[float, str]:
    """Factor from model units and the unit shown: bias in mg or °/s, scale-factor error in ppm."""
    return DISPLAY[triad] if term == "bias" else (PPM, "ppm")


def term_curve(tp: TriadPoly, axis: int, term: str, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fitted term at the given temperatures and its 1-sigma uncertainty (nan when unknown).

    The band comes from the coefficients' covariance (`p(T)' C p(T)`), not from their standard
    deviations alone: the coefficients of a polynomial are strongly correlated."""
    m = tp.order + 1
    block = 0 if term == "bias" else 1 + axis
    coef = tp.coefficients()[axis, block * m:(block + 1) * m]
    p = tp.powers(temp_c)
    value = p @ coef
    sd = np.full(temp_c.shape, np.nan)
    if tp.coef_cov is not None:
        cov = tp.coef_cov[axis, block * m:(block + 1) * m, block * m:(block + 1) * m]
        if np.all(np.isfinite(cov)):
            sd = np.sqrt(np.clip(np.einsum("nk,kl,nl->n", p, cov, p), 0.0, None))
    return value, sd


def thermal_figure(result: FitResult, triad: str, term: str) -> Figure:
    """Bias or scale-factor error vs temperature per axis: six-position estimates per step (points,
    ±1σ bars), the fitted polynomial (line, ±1σ band), and on the right what the polynomial misses."""
    tp = result.polynomial.triads()[triad]
    cals = result.models.six_position[triad]
    factor, unit = term_units(triad, term)
    temps = np.array([c.temp_c for c in cals])
    grid = np.linspace(tp.t_min_c, tp.t_max_c, 161)
    fig, axes = new_figure(3, 2, (10, 8.2), sharex=True, gridspec_kw={"width_ratios": [2.2, 1]}, left=1.0,
                           top=0.75, bottom=0.55, hspace=0.3, wspace=0.32)
    spans: dict[str, float] = {}
    for i, axis in enumerate(AXES):
        ax, res_ax = axes[i]
        block = 0 if term == "bias" else 1 + i
        if term == "bias":
            pts = np.array([c.bias[i] for c in cals]) * factor
            err = np.array([c.bias_std[i] for c in cals]) * factor
        else:
            pts = np.array([c.scale[i, i] for c in cals]) * factor
            err = np.array([c.scale_std[i, i] for c in cals]) * factor
        ok = np.isfinite(pts)
        ax.set_ylabel(f"{TERMS[term]} {axis} ({unit})")
        res_ax.set_ylabel(f"residual ({unit})")
        if not tp.fitted[i, block]:
            ax.text(0.5, 0.5, f"{TERMS[term]} {axis} not fitted", transform=ax.transAxes, ha="center",
                    va="center")
            ax.set_title(f"{axis}: not fitted")
            continue
        value, sd = term_curve(tp, i, term, grid)
        value, sd = value * factor, sd * factor
        spans[axis] = float(np.ptp(value))
        ax.plot(grid, value, color=colour("polynomial"), lw=2,
                label=f"{tp.method} polynomial, order {tp.order}")
        if np.isfinite(sd).all():
            ax.fill_between(grid, value - sd, value + sd, color=colour("polynomial"), alpha=0.25,
                            label="±1σ of the polynomial")
        ax.errorbar(temps[ok], pts[ok], yerr=np.nan_to_num(err[ok]), fmt="o", color="black", ms=5, capsize=3,
                    label="six-position estimate per step (±1σ)")
        at_ref, _ = term_curve(tp, i, term, np.array([tp.t_ref_c]))
        slope = (value[-1] - value[0]) / (grid[-1] - grid[0]) if grid[-1] > grid[0] else float("nan")
        ax.set_title(f"{axis}: {fmt(at_ref[0] * factor, 4)} {unit} at {tp.t_ref_c:g} °C, "
                     f"{fmt(slope)} {unit}/°C on average", fontsize=10)
        # The residual panel makes the band and the bars visible: next to the thermal change they are tiny.
        fit_at_pts, sd_pts = term_curve(tp, i, term, temps[ok])
        if np.isfinite(sd).all():
            res_ax.fill_between(grid, -sd, sd, color=colour("polynomial"), alpha=0.25)
        res_ax.axhline(0.0, color=colour("polynomial"), lw=1)
        res_ax.errorbar(temps[ok], pts[ok] - fit_at_pts * factor, yerr=np.nan_to_num(err[ok]), fmt="o",
                        color="black", ms=4, capsize=3)
    if not spans:
        raise FigureSkipped(f"no {TERMS[term]} of the {triad} could be fitted")
    axes[0, 0].legend(fontsize=8, loc="best")
    axes[-1, 0].set_xlabel("IMU temperature (°C)")
    axes[-1, 1].set_xlabel("IMU temperature (°C)")
    worst = max(spans, key=spans.__getitem__)
    axes[0, 1].set_title("estimate − polynomial, ±1σ", fontsize=10)
    headline(fig, f"{TRIAD_TITLES[triad]} {TERMS[term]} vs temperature: {worst} changes most, "
                  f"{fmt(spans[worst])} {unit} over {tp.t_min_c:.1f} … {tp.t_max_c:.1f} °C")
    return fig


def heldout_error_figure(result: FitResult, triad: str) -> Figure:
    """RMS error on held-out samples per axis, raw and after every compensation, one panel per split
    (log scale: the gains span orders of magnitude). Ticks mark the RMS of the held-out record means,
    the systematic error without the sensor noise."""
    if not result.evaluation:
        raise FigureSkipped("no evaluation ran (--no-eval)")
    ran = [s for s in result.evaluation if not s.skipped and "raw" in s.samples]
    if not ran:
        raise FigureSkipped("every evaluation split was skipped")
    factor, unit = DISPLAY[triad]
    sl = TRIAD_SLICE[triad]
    h = fit_headline(result)
    fig, axes = new_figure(len(ran), 1, (10, 1.5 + 2.6 * len(ran)), sharex=True, top=0.7, bottom=0.85,
                           hspace=0.3)
    for ax, split in zip(axes[:, 0], ran):
        models = list(split.samples)
        width = 0.8 / len(models)
        for k, name in enumerate(models):
            x = np.arange(3) + (k - (len(models) - 1) / 2) * width
            rms = split.samples[name].rms[sl] * factor
            ax.bar(x, rms, width, color=colour(name), label=name,
                   edgecolor="black" if name == h.exported else "none", linewidth=1.5)
            rec = split.records[name].rms[sl] * factor
            ax.plot(x, rec, linestyle="none", marker="_", ms=10, mew=2, color="black")
        ax.set_yscale("log")
        ax.set_ylabel(f"RMS error ({unit})")
        ax.set_title(f"{split.name}: {split.description}", fontsize=10)
    axes[0, 0].plot([], [], linestyle="none", marker="_", ms=10, mew=2, color="black", label="record means")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="lower center", ncol=len(labels))  # bars fill the panels
    axes[-1, 0].set_xticks(np.arange(3), [f"{triad} {a}" for a in AXES])
    axes[-1, 0].set_xlabel("axis (bars: held-out samples; black ticks: held-out record means)")
    g = h.gains[triad]
    headline(fig, f"{TRIAD_TITLES[triad]} held-out error: RMS {fmt(g.raw_rms * factor)} {unit} raw → "
                  f"{fmt(g.exported_rms * factor)} {unit} {h.exported} ({-g.gain_vs_raw_pct:+.0f} %, "
                  f"{h.split.name if h.split else '?'})")
    return fig
