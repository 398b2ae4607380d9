"""What the fit's figures share: a blank figure without pyplot, model colours, display units.

Figures are `matplotlib.figure.Figure` objects made directly, never through pyplot: no global
state, no display or backend needed (saving to PNG uses Agg), safe in the sequencer's process.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from matplotlib.figure import Figure


class FigureSkipped(Exception):
    """A figure the fit's data cannot support; the message says why (it goes into the summary)."""


# One colour per model in every figure, so a reader learns them once.
MODEL_COLOURS: dict[str, str] = {
    "raw": "#7f7f7f", "polynomial": "#1f77b4", "polynomial_two_stage": "#9ecae1", "polynomial_joint": "#9ecae1",
    "rbf_paper": "#ff7f0e", "rbf_triad": "#2ca02c", "rbf_hybrid": "#d62728",
}
TRIAD_TITLES = {"accel": "Accelerometer", "gyro": "Gyroscope"}
# Display units: the paper's mg for the accelerometer; deg/s for the gyro (model units are g, deg/s).
DISPLAY = {"accel": (1e3, "mg"), "gyro": (1.0, "°/s")}
DPI = 100


def colour(model: str) -> str:
    return MODEL_COLOURS.get(model, "#8c564b")


def new_figure(rows: int, cols: int, size: tuple[float, float], *, left: float = 0.85, right: float = 0.25,
               top: float = 0.75, bottom: float = 0.6, hspace: float = 0.35, wspace: float = 0.25,
               **subplots: Any) -> tuple[Figure, np.ndarray]:
    """A figure and its axes as a 2-D array, margins in inches.

    Fixed margins, not constrained layout: the figures run at the end of every fit, and measuring
    every label to place the axes more than doubled the drawing time. Each figure's margins are
    sized for its labels (checked by looking at them)."""
    w, h = size
    fig = Figure(figsize=size)
    axes = fig.subplots(rows, cols, squeeze=False, **subplots)
    fig.subplots_adjust(left=left / w, right=1 - right / w, top=1 - top / h, bottom=bottom / h, hspace=hspace,
                        wspace=wspace)
    return fig, axes


def headline(fig: Figure, text: str) -> None:
    """The figure's title: what it shows and the key number, in bold at the top."""
    w, h = fig.get_size_inches()
    fig.suptitle(text, y=1 - 0.22 / h, fontsize=11.5, fontweight="bold")


def decimation(n: int, max_points: int) -> int:
    """Keep every k-th of n points so that at most max_points remain (plots need no more)."""
    return max(1, -(-n // max_points))


def fmt(v: float, digits: int = 3) -> str:
    """`digits` significant digits, without an exponent for values a reader takes in at a glance
    (13500 ppm, not 1.35e+04 ppm)."""
    if not np.isfinite(v):
        return "-"
    if v == 0 or not 1e-3 <= abs(v) < 1e6:
        return f"{v:.{digits}g}"
    decimals = digits - 1 - int(np.floor(np.log10(abs(v))))
    return f"{round(v, decimals):.{max(decimals, 0)}f}"
