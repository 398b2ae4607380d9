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
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

from matplotlib.figure import Figure

from .figure_style import DPI, FigureSkipped
from .figures_fit import heldout_error_figure, thermal_figure
from .figures_static import StaticSamples, allan_curves, allan_figure, static_norm_figure, static_samples
from .fit import FitResult

log = logging.getLogger(__name__)

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


def write_figures(result: FitResult, out: Path) -> FigureReport:
    """Draw every figure the fit supports into `out` (PNG); never raises for a figure."""
    report = FigureReport()
    out.mkdir(parents=True, exist_ok=True)
    for name, what, build in _figure_builders(result):
        t0 = time.perf_counter()
        try:
            fig = build()
            fig.savefig(out / name, dpi=DPI)
            report.written[name] = what
        except FigureSkipped as exc:
            report.skipped[name] = str(exc)
        except Exception as exc:  # a figure is a view of the fit: it must not cost the models
            log.warning("figure %s not drawn: %s: %s", name, type(exc).__name__, exc,
                        exc_info=log.isEnabledFor(logging.DEBUG))
            report.skipped[name] = f"could not be drawn ({type(exc).__name__}: {exc})"
        report.seconds[name] = time.perf_counter() - t0
    report.skipped.update(NOT_DRAWN)
    log.info("figures: %d written, %d skipped in %.1f s", len(report.written), len(report.skipped),
             sum(report.seconds.values()))
    return report
