"""The paper's figures from a fit, as PNG files next to the models.

| file | paper | what |
|---|---|---|
| thermal_accel_bias.png, thermal_accel_scale.png | Figs. 3-4 | accelerometer bias / scale-factor error vs T |
| thermal_gyro_bias.png, thermal_gyro_scale.png | Figs. 5-6 | gyro bias / scale-factor error vs T |
| heldout_error_accel.png, heldout_error_gyro.png | Figs. 7-8 | held-out error before and after each model |
| static_norm_accel.png, static_norm_gyro.png | Figs. 10-11 | norms of static samples before and after |
| allan_deviation.png | - | Allan deviation per channel on the longest static records |

A figure never breaks a fit: one the data cannot support (no evaluation, no static records) or
that fails to draw is skipped, and `FigureReport.skipped` says why (the summary lists it).
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import matplotlib as mpl
from matplotlib import ticker
from matplotlib.figure import Figure

from labrunner.forked import balanced_groups, configured_processes, fork_map

from .figure_style import DPI, FigureSkipped
from .figures_fit import heldout_error_figure, thermal_figure
from .figures_static import StaticSamples, allan_curves, allan_figure, static_norm_figure, static_samples
from .fit import FitResult

log = logging.getLogger(__name__)

# Titles at the top of their axes (axes.titley None would move each title clear of anything drawn above
# the axes: no figure here draws anything there, and finding that out measured every tick label of every
# axes, a third of the drawing time).
_RC: dict[Any, Any] = {"axes.titley": 1.0}  # (rc_context takes literal keys only)

_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")
_MATHTEXT_POWER = re.compile(r"\$\\mathdefault\{(?:(\d+(?:\.\d+)?)\\times)?(\d+)\^\{(-?\d+)\}\}\$")


def plain_power(label: str) -> str:
    """A log axis' tick label `$\\mathdefault{2\\times10^{-3}}$` as plain text, 2×10⁻³ (others as they are)."""
    m = _MATHTEXT_POWER.fullmatch(label)
    if m is None:
        return label
    coeff, base, exponent = m.groups()
    return (f"{coeff}×" if coeff else "") + base + exponent.translate(_SUPERSCRIPT)


class _PlainLogFormatter(ticker.Formatter):
    """A log axis' own formatter (which ticks get a label, and which), its labels as plain text: mathtext
    labels are parsed by pyparsing, ~20 ms each, most of what a log-scaled figure costs to draw."""

    def __init__(self, inner: ticker.Formatter) -> None:
        self.inner = inner

    def set_axis(self, axis: object) -> None:
        super().set_axis(axis)  # type: ignore[arg-type]
        self.inner.set_axis(axis)  # type: ignore[arg-type]

    def set_locs(self, locs: object) -> None:
        self.inner.set_locs(locs)  # type: ignore[arg-type]

    def __call__(self, x: float, pos: int | None = None) -> str:
        return plain_power(self.inner(x, pos))


def plain_log_labels(fig: Figure) -> None:
    """Label every log-scaled axis of the figure in plain text (same ticks, same labels)."""
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() != "log":
                continue
            if isinstance(axis.get_major_formatter(), ticker.LogFormatterMathtext):
                axis.set_major_formatter(_PlainLogFormatter(axis.get_major_formatter()))
            if isinstance(axis.get_minor_formatter(), ticker.LogFormatterMathtext):
                axis.set_minor_formatter(_PlainLogFormatter(axis.get_minor_formatter()))

# Not drawn by design, said in every report: the evaluation does not navigate.
NOT_DRAWN = {"ins_position_error.png (paper Fig. 14)": "the evaluation does not integrate an INS solution, "
                                                      "so there is no position error to plot"}


@dataclass
class FigureReport:
    """What `write_figures` wrote and what it skipped, with reasons and drawing times."""

    written: dict[str, str] = field(default_factory=dict)  # file name -> what it shows
    skipped: dict[str, str] = field(default_factory=dict)  # file name -> why not drawn
    seconds: dict[str, float] = field(default_factory=dict)

    def markdown(self) -> str:
        out = ["## Figures", ""]
        out += [f"- `{name}`: {what}" for name, what in self.written.items()]
        out += [f"- not drawn: `{name}`: {why}" for name, why in self.skipped.items()]
        return "\n".join(out)


def _figure_builders(result: FitResult) -> list[tuple[str, str, Callable[[], Figure]]]:
    """(file name, description, builder) in the paper's order; builders raise FigureSkipped."""
    cache: dict[str, StaticSamples | FigureSkipped] = {}

    def samples() -> StaticSamples:
        # Shared by both norm figures: compensating the static rows once is enough.
        if "s" not in cache:
            try:
                cache["s"] = static_samples(result)
            except FigureSkipped as exc:
                cache["s"] = exc
        got = cache["s"]
        if isinstance(got, FigureSkipped):
            raise got
        return got

    def norm_figure(triad: str) -> Figure:
        return static_norm_figure(samples(), triad)

    out: list[tuple[str, str, Callable[[], Figure]]] = []
    thermal = (("accel", "bias"), ("accel", "scale"), ("gyro", "bias"), ("gyro", "scale"))
    for fig_no, (triad, term) in enumerate(thermal, start=3):
        what = "bias" if term == "bias" else "scale-factor error"
        out.append((f"thermal_{triad}_{term}.png", f"{triad} {what} vs temperature (paper Fig. {fig_no})",
                    partial(thermal_figure, result, triad, term)))
    for fig_no, triad in ((7, "accel"), (8, "gyro")):
        out.append((f"heldout_error_{triad}.png",
                    f"{triad} error on held-out data before and after each compensation (paper Fig. {fig_no})",
                    partial(heldout_error_figure, result, triad)))
    for fig_no, triad in ((10, "accel"), (11, "gyro")):
        out.append((f"static_norm_{triad}.png",
                    f"norm of the {'specific force' if triad == 'accel' else 'angular rate'} on static samples "
                    f"before and after compensation (paper Fig. {fig_no})", partial(norm_figure, triad)))
    out.append(("allan_deviation.png", "Allan deviation per channel on the longest static records",
                lambda: allan_figure(allan_curves(result))))
    return out


# Drawing time of each figure on the paper campaign (s), to share the figures among processes: the
# thermal and held-out figures 0.4-0.75, the two norm figures 0.35 together, the Allan deviation 1.0.
_SECONDS = {"allan_deviation.png": 1.0, "heldout_error_gyro.png": 0.75, "static_norm": 0.35}


def write_figures(result: FitResult, out: Path) -> FigureReport:
    """Draw every figure the fit supports into `out` (PNG); never raises for a figure. The figures are
    drawn in up to `forked.configured_processes()` processes (the norm figures, which share their
    compensated rows, in one), and reported in the paper's order."""
    out.mkdir(parents=True, exist_ok=True)
    builders = _figure_builders(result)
    tasks: dict[str, list[tuple[str, str, Callable[[], Figure]]]] = {}
    for b in builders:
        tasks.setdefault("static_norm" if b[0].startswith("static_norm") else b[0], []).append(b)
    keys = list(tasks)
    groups = balanced_groups([_SECONDS.get(k, 0.45) for k in keys], min(configured_processes(), len(keys)))
    parts = fork_map(lambda g: _draw([b for i in g for b in tasks[keys[i]]], out), groups)
    written = {k: v for p in parts for k, v in p.written.items()}
    skipped = {k: v for p in parts for k, v in p.skipped.items()}
    seconds = {k: v for p in parts for k, v in p.seconds.items()}
    names = [b[0] for b in builders]  # the paper's order, whichever process drew a figure
    report = FigureReport(written={n: written[n] for n in names if n in written},
                          skipped={n: skipped[n] for n in names if n in skipped} | NOT_DRAWN,
                          seconds={n: seconds[n] for n in names})
    log.info("figures: %d written, %d skipped in %.1f s", len(report.written), len(report.skipped),
             sum(report.seconds.values()))
    return report


def _draw(builders: list[tuple[str, str, Callable[[], Figure]]], out: Path) -> FigureReport:
    report = FigureReport()
    for name, what, build in builders:
        t0 = time.perf_counter()
        try:
            with mpl.rc_context(_RC):  # axes made and drawn inside: the setting is read by both
                fig = build()
                plain_log_labels(fig)
                fig.savefig(out / name, dpi=DPI)
            report.written[name] = what
        except FigureSkipped as exc:
            report.skipped[name] = str(exc)
        except Exception as exc:  # a figure is a view of the fit: it must not cost the models
            log.warning("figure %s not drawn: %s: %s", name, type(exc).__name__, exc,
                        exc_info=log.isEnabledFor(logging.DEBUG))
            report.skipped[name] = f"could not be drawn ({type(exc).__name__}: {exc})"
        report.seconds[name] = time.perf_counter() - t0
    return report
