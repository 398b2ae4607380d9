"""The headline of a fit: which model is exported and how much it gains on held-out data.

One number per triad keeps it readable at a glance: the RMS error of the held-out samples over
the three axes, `sqrt(mean_i rms_i^2)`, from the same `ErrorStats` the tables print. The gain
is the paper's improvement, `100 (1 - model / reference)`, applied to that RMS. The split quoted
is the most telling one that ran: held-out temperature steps say how the model does between
calibrated temperatures; the random split mostly measures the fit itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .evaluation import SplitResult
from .fit import FitResult
from .triads import TRIAD_SLICE, TRIADS

# Most telling first: interpolation in temperature, then the paper's random split.
HEADLINE_SPLITS: tuple[str, ...] = ("between_temperatures", "random", "beyond_temperatures", "between_rates",
                                     "time_blocks")


@dataclass(frozen=True)
class TriadGain:
    """Held-out RMS error of one triad before and after compensation."""

    triad: str
    raw_rms: float
    polynomial_rms: float
    exported_rms: float  # the exported RBF network, or the polynomial when no network is exported
    best_model: str  # lowest RMS among all scored models
    best_rms: float

    @property
    def gain_vs_raw_pct(self) -> float:
        return gain_pct(self.exported_rms, self.raw_rms)

    @property
    def gain_vs_polynomial_pct(self) -> float:
        return gain_pct(self.exported_rms, self.polynomial_rms)


@dataclass(frozen=True)
class Headline:
    """What the first lines of the summary say."""

    exported: str  # evaluation name of the exported model: "rbf_hybrid", or "polynomial"
    polynomial: str  # e.g. "joint, order 3"
    split: SplitResult | None  # the split quoted; None when no evaluation ran
    gains: dict[str, TriadGain]  # triad -> gain (empty without a split)


def gain_pct(model: float, reference: float) -> float:
    """The paper's improvement in %: 100 (1 - model / reference)."""
    if not (np.isfinite(model) and np.isfinite(reference)) or reference == 0:
        return float("nan")
    return 100.0 * (1.0 - model / reference)


def triad_rms(split: SplitResult, model: str, triad: str) -> float:
    """RMS of the held-out sample errors over the triad's three axes."""
    rms = split.samples[model].rms[TRIAD_SLICE[triad]]
    return float(np.sqrt(np.mean(rms ** 2)))


def headline_split(result: FitResult) -> SplitResult | None:
    ran = {s.name: s for s in result.evaluation if not s.skipped and "raw" in s.samples}
    for name in HEADLINE_SPLITS:
        if name in ran:
            return ran[name]
    return next(iter(ran.values()), None)


def exported_name(result: FitResult) -> str:
    return f"rbf_{result.options.rbf_export}" if result.rbf is not None else "polynomial"


def headline(result: FitResult) -> Headline:
    tps = result.polynomial.triads()
    methods = {tp.method for tp in tps.values()}
    orders = {tp.order for tp in tps.values()}
    poly = f"{'/'.join(sorted(methods))}, order " + (
        str(orders.pop()) if len(orders) == 1 else f"{tps['accel'].order} accel, {tps['gyro'].order} gyro")
    split = headline_split(result)
    exported = exported_name(result)
    gains: dict[str, TriadGain] = {}
    if split is not None:
        scored = [m for m in split.samples if m != "raw"]
        for triad in TRIADS:
            rms = {m: triad_rms(split, m, triad) for m in scored}
            best = min(rms, key=lambda m: rms[m] if np.isfinite(rms[m]) else np.inf)
            gains[triad] = TriadGain(
                triad=triad, raw_rms=triad_rms(split, "raw", triad), polynomial_rms=rms["polynomial"],
                exported_rms=rms.get(exported, rms["polynomial"]), best_model=best, best_rms=rms[best])
    return Headline(exported=exported, polynomial=poly, split=split, gains=gains)
