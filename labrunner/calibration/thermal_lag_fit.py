"""Calibrating with the thermal lag of the sensing element (issue 11 item 6, issue 16 item 2).

The element lags the IMU's temperature sensor by a first-order lag of time constant tau (the
simulator's `labrunner.imu.effects.thermal_lag`, the diagnosis's finding `thermal_lag`). On a ramp of
rate r every record then reads its thermal terms at T - r*tau, and a fit against the logged
temperature is biased by slope * r * tau. On a serpentine ramp campaign (one orientation heating, the
next cooling) the accelerometer absorbs that bias into its scale factor and misalignment without a
residual and is wrong by it at rest; the gyro, whose bias is common to all orientations, shows it as a
heating/cooling inconsistency. So the fit uses the lag-corrected temperature: the logged temperature
through the same first-order filter (`first_order_lag`, the simulator's), and the exported models carry
the filter (`TemperatureFilter`: JSON `temperature_filter`, a filter state in the C header) so that
`labrunner compensate` and the firmware feed them the same temperature.

tau is configured (`fit.thermal_lag_s`, `labrunner fit --thermal-lag S`, e.g. from the diagnosis's
finding) or searched (`auto`): a 1-D search over tau of the joint polynomial's record residual, each
channel's residual relative to its residual without a lag. The lag-corrected fit is compared with the
plain one on the held-out splits both ran and used only when it gains (`LagReport`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from labrunner.errors import UserError
from labrunner.imu.recursions import first_order_lag

from .records import Records, frame_arrays, temperature_steps
from .thermal_poly import fit_joint, max_order
from .triads import TRIADS

if TYPE_CHECKING:
    from .fit import FitOptions, FitResult

log = logging.getLogger(__name__)

FILTER_KIND = "first_order_lag"
MAX_TAU_S = 86400.0
# The search grid: no lag, then 10 s .. 1 h geometrically; the best point is refined in log tau.
SEARCH_GRID_S: tuple[float, ...] = (0.0, *np.round(np.geomspace(10.0, 3600.0, 12), 1).tolist())
REFINE_STEPS = 8  # golden-section steps: the bracket shrinks to 0.618^8 ~ 2 % of two grid steps
# Held-out RMS of the exported model, lag-corrected over plain, must be below this (mean over the
# triads and splits both ran) for the lag-corrected model to be used.
USE_IF_RATIO_BELOW = 1.0
# A gap in the log at least this many tau long restarts the filter (`lag_corrected_temperature`): the
# filter's memory of the rows before it has decayed to exp(-1), and what the sensor did in it is unknown.
RESTART_GAP_TAUS = 1.0


@dataclass(frozen=True)
class TemperatureFilter:
    """The temperature a model is evaluated at: the logged one through dy/dt = (x - y)/tau.

    `sample_period_s` is the fit data's typical row interval: the C header's fixed-period update uses
    it (the device calls the update at its sample rate); Python filters at the rows' own times.
    """

    tau_s: float
    sample_period_s: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.tau_s) and 0.0 < self.tau_s <= MAX_TAU_S):
            raise ValueError(f"temperature filter: tau_s must be in (0, {MAX_TAU_S:g}] s, not {self.tau_s!r}")
        if not (np.isfinite(self.sample_period_s) and self.sample_period_s > 0.0):
            raise ValueError(f"temperature filter: sample_period_s must be > 0, not {self.sample_period_s!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"kind": FILTER_KIND, "tau_s": float(self.tau_s), "sample_period_s": float(self.sample_period_s),
                "input": "imu_temp_c", "what": "dy/dt = (imu_temp_c - y) / tau_s, per run, started at the run's "
                "first temperature; the model's temperature is y. A log with a gap of tau_s or more restarts it "
                "after the gap at x - slope * tau_s (a device filters without gaps)"}

    @classmethod
    def from_dict(cls, d: Any) -> TemperatureFilter:
        if not isinstance(d, dict) or d.get("kind") != FILTER_KIND:
            raise ValueError(f"temperature_filter: expected kind {FILTER_KIND!r}")
        return cls(tau_s=float(d["tau_s"]), sample_period_s=float(d["sample_period_s"]))

    @property
    def alpha(self) -> float:
        """Per-sample decay exp(-dt/tau) at the sample period."""
        return float(np.exp(-self.sample_period_s / self.tau_s))

    @property
    def beta(self) -> float:
        """(1 - alpha) tau / dt: the first-order-hold weight of the input's change over a sample."""
        return float(-np.expm1(-self.sample_period_s / self.tau_s) * self.tau_s / self.sample_period_s)

    def apply(self, t_s: np.ndarray, temp_c: np.ndarray, run: np.ndarray | None = None) -> np.ndarray:
        return lag_corrected_temperature(t_s, temp_c, run, self.tau_s)


def lag_corrected_temperature(t_s: np.ndarray, temp_c: np.ndarray, run: np.ndarray | None,
                              tau_s: float) -> np.ndarray:
    """The element temperature: the logged temperature through a first-order lag of `tau_s`, restarted
    (settled at its first temperature) at each run, as the device's filter starts at power-on. Rows are
    taken in time order within each run (the input need not be sorted); between rows the temperature is
    taken as linear, which is exact on a ramp and what a log with short gaps between records allows.

    A gap of at least `RESTART_GAP_TAUS` x tau_s (a log of records only: the chamber moved and soaked
    between two temperatures, unlogged) is not bridged: a straight line over it would make the record
    after it lag by (change / gap) x tau, behind a sensor that in fact soaked (about 0.5 C at the first
    record of a soak after a 2 h move of 15 C), in heating and cooling alike with opposite signs. The
    filter, which on a device runs through the gap, has forgotten its state there; it restarts at the
    steady state of a line through the rows after the gap: x0 - r tau, with r their slope over tau_s
    (0 on a soak; exact on a ramp)."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(temp_c, dtype=float)
    out = np.empty_like(x)
    if x.size == 0:
        return out
    runs = np.zeros(x.size, dtype=np.int64) if run is None else np.asarray(run)
    dr = np.diff(runs)
    if np.all(dr >= 0) and np.all((np.diff(t) >= 0) | (dr != 0)):  # in order already (a store's rows are)
        order = np.arange(x.size)
    else:
        order = np.lexsort((t, runs))
    ts, xs, rs = t[order], x[order], runs[order]
    new_run = np.diff(rs) != 0
    gap = ~new_run & (np.diff(ts) >= RESTART_GAP_TAUS * tau_s)
    cuts = np.flatnonzero(new_run | gap) + 1
    restarts = set((np.flatnonzero(gap) + 1).tolist())
    ys = np.empty_like(xs)
    for a, b in zip(np.concatenate(([0], cuts)), np.concatenate((cuts, [xs.size])), strict=True):
        if a in restarts:
            y0 = float(xs[a]) - _start_slope(ts[a:b], xs[a:b], tau_s) * tau_s
            ys[a:b] = first_order_lag(ts[a:b], xs[a:b], tau_s, y0=y0, x0=float(xs[a]), t0=float(ts[a]))
        else:
            ys[a:b] = first_order_lag(ts[a:b], xs[a:b], tau_s)
    out[order] = ys
    return out


def _start_slope(t: np.ndarray, x: np.ndarray, window_s: float) -> float:
    """Least-squares slope (C/s) of the rows within `window_s` of the first (0 with fewer than two times)."""
    n = int(np.searchsorted(t, t[0] + window_s, side="right"))
    tt, xx = t[:n] - t[0], x[:n]
    if n < 2 or tt[-1] <= 0:
        return 0.0
    dt = tt - tt.mean()
    return float(np.dot(dt, xx - xx.mean()) / np.dot(dt, dt))


def with_temperature(frame: pd.DataFrame, tau_s: float) -> pd.DataFrame:
    """The frame with `imu_temp_c` lag-corrected (a new frame; the other columns are shared)."""
    temp = lag_corrected_temperature(frame["t_s"].to_numpy(dtype=float), frame["imu_temp_c"].to_numpy(dtype=float),
                                     frame["run"].to_numpy(), tau_s)
    return frame.assign(imu_temp_c=temp)


DIAGNOSIS_PREFIX = "from:"  # `fit --thermal-lag from:DIAG.json`: tau of the diagnosis's thermal_lag finding


@dataclass(frozen=True)
class DiagnosedLag:
    """The thermal lag a diagnosis found (`labrunner diagnose --json`): its finding's tau and status."""

    tau_s: float
    status: str  # "selected", or "alternative" (confounded with a selected cause)
    channels: list[str]
    path: str

    def sentence(self) -> str:
        return (f"thermal lag tau = {self.tau_s:.1f} s from the diagnosis {self.path} (finding thermal_lag, "
                f"{self.status}, channels {', '.join(self.channels) or '?'})")


def lag_from_diagnosis(path: str | Path) -> DiagnosedLag:
    """The `thermal_lag` finding of a diagnosis JSON (`findings[].cause == "thermal_lag"`,
    `parameters.tau_s`): the selected one, else an alternative; a one-line `UserError` otherwise."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        raise UserError(f"--thermal-lag {DIAGNOSIS_PREFIX}{p}: no such file") from None
    except IsADirectoryError:
        raise UserError(f"--thermal-lag {DIAGNOSIS_PREFIX}{p}: is a directory; expected the JSON of "
                        "`labrunner diagnose --json`") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"--thermal-lag {DIAGNOSIS_PREFIX}{p}: not JSON ({exc}); expected the JSON of "
                        "`labrunner diagnose --json`") from None
    findings = doc.get("findings") if isinstance(doc, dict) else None
    if not isinstance(findings, list):
        raise UserError(f"--thermal-lag {DIAGNOSIS_PREFIX}{p}: no 'findings' list; expected the JSON of "
                        "`labrunner diagnose --json`")
    lags = [f for f in findings if isinstance(f, dict) and f.get("cause") == "thermal_lag"]
    if not lags:
        causes = ", ".join(str(f.get("cause")) for f in findings if isinstance(f, dict)) or "none"
        raise UserError(f"--thermal-lag {DIAGNOSIS_PREFIX}{p}: the diagnosis found no thermal_lag (its findings: "
                        f"{causes}); give a time constant or 'auto'")
    best = next((f for f in lags if f.get("status") == "selected"), lags[0])
    tau = (best.get("parameters") or {}).get("tau_s")
    if isinstance(tau, bool) or not isinstance(tau, int | float) or not (0.0 < float(tau) <= MAX_TAU_S):
        raise UserError(f"--thermal-lag {DIAGNOSIS_PREFIX}{p}: the thermal_lag finding's parameters.tau_s is "
                        f"{tau!r}, not a time constant in (0, {MAX_TAU_S:g}] s")
    return DiagnosedLag(float(tau), str(best.get("status", "?")), [str(c) for c in best.get("channels") or []],
                        str(p))


@dataclass
class LagSearch:
    """The 1-D search of tau: score (mean over channels of the record residual's mean square, relative
    to no lag) at every tau tried."""

    tau_s: list[float]
    score: list[float]
    best_tau_s: float

    def to_dict(self) -> dict[str, Any]:
        return {"tau_s": self.tau_s, "score": self.score, "best_tau_s": self.best_tau_s}


def _residual_ms(a: dict[str, np.ndarray], records: Records, tau_s: float, opt: FitOptions) -> np.ndarray:
    """(6,) weighted mean square of the joint polynomial's record residuals with the element temperature
    at lag `tau_s`. The records keep their rows and output means; only their temperatures move."""
    recs = records
    if tau_s > 0:
        temp = lag_corrected_temperature(a["t"], a["temp"], a["run"], tau_s)
        sel = records.row_record >= 0
        lab = records.row_record[sel]
        mean_t = np.bincount(lab, weights=temp[sel], minlength=len(records)) / np.maximum(
            np.bincount(lab, minlength=len(records)), 1)
        recs = replace(records, temp_c=mean_t)
    ro = opt.records
    steps = temperature_steps(recs, ro.step_gap_c, ro.max_step_width_c, ro.continuous_gap_c, ro.ramp_bin_c)
    order = max_order(len(steps), int(opt.poly_order) if opt.poly_order != "cv" else 3)
    out = []
    for triad in TRIADS:
        offsets = triad == "gyro" and len(set(recs.run.tolist())) > 1
        p = fit_joint(recs, triad, order, opt.t_ref_c, run_offsets=offsets)
        out.append(np.asarray(p.residual_rms, dtype=float) ** 2)
    return np.concatenate(out)


def search_tau(frame: pd.DataFrame, records: Records, opt: FitOptions,
               progress: Callable[[str], None] | None = None) -> LagSearch:
    """The tau minimising the joint polynomial's record residual (records as segmented without a lag)."""
    a = frame_arrays(frame)
    records = replace(records, step=records.step.copy())  # temperature_steps sets the step labels in place
    cache: dict[float, float] = {}
    base = _residual_ms(a, records, 0.0, opt)
    ok = np.isfinite(base) & (base > 0)
    if not ok.any():
        raise UserError("thermal lag search: the records leave no residual to search on")

    def score(tau: float) -> float:
        tau = round(float(tau), 2)
        if tau not in cache:
            ms = base if tau <= 0 else _residual_ms(a, records, tau, opt)
            cache[tau] = float(np.mean(ms[ok] / base[ok]))
        return cache[tau]

    if progress:
        progress(f"thermal lag: searching tau over {len(SEARCH_GRID_S)} values")
    grid = [score(t) for t in SEARCH_GRID_S]
    k = int(np.argmin(grid))
    best = SEARCH_GRID_S[k]
    if k > 0:  # golden-section refinement in log tau between the neighbours of the best grid point
        lo = np.log(SEARCH_GRID_S[k - 1]) if k > 1 else np.log(SEARCH_GRID_S[1]) - 0.5
        hi = np.log(SEARCH_GRID_S[k + 1]) if k + 1 < len(SEARCH_GRID_S) else np.log(SEARCH_GRID_S[k]) + 0.5
        g = (np.sqrt(5.0) - 1.0) / 2.0
        c, d = hi - g * (hi - lo), lo + g * (hi - lo)
        for _ in range(REFINE_STEPS):
            if score(np.exp(c)) < score(np.exp(d)):
                hi, d = d, c
                c = hi - g * (hi - lo)
            else:
                lo, c = c, d
                d = lo + g * (hi - lo)
        best = min(cache, key=lambda t: cache[t])
    taus = sorted(cache)
    return LagSearch(tau_s=taus, score=[cache[t] for t in taus], best_tau_s=float(best))


@dataclass
class LagReport:
    """What the fit did with the thermal lag: tau and where it came from, the held-out RMS of the exported
    model with and without the lag correction, and whether the lag-corrected model is the one exported."""

    tau_s: float
    source: str  # "configured" or "auto"
    used: bool
    reason: str
    heldout: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)  # split -> triad -> plain/lagged
    ratio: float | None = None  # mean over splits and triads of lagged / plain
    search: LagSearch | None = None
    sample_period_s: float = 0.0

    @property
    def temperature_filter(self) -> TemperatureFilter | None:
        return TemperatureFilter(self.tau_s, self.sample_period_s) if self.used else None

    def sentence(self) -> str:
        how = "configured" if self.source == "configured" else "searched (record residual)"
        gain = "" if self.ratio is None else f"; held-out RMS lag-corrected / plain {self.ratio:.3f}"
        verdict = "used: the models take the lag-corrected temperature" if self.used else "not used"
        return f"thermal lag tau = {self.tau_s:.1f} s ({how}){gain}: {verdict} ({self.reason})"

    def to_dict(self) -> dict[str, Any]:
        return {"tau_s": self.tau_s, "source": self.source, "used": self.used, "reason": self.reason,
                "heldout_record_rms": self.heldout, "ratio_lagged_to_plain": self.ratio,
                "search": self.search.to_dict() if self.search else None,
                "temperature_filter": TemperatureFilter(self.tau_s, self.sample_period_s).to_dict()
                if self.used else None}


def _exported_rms(result: FitResult) -> dict[str, dict[str, float]]:
    """split -> triad -> RMS over x, y, z of the held-out record means of the exported model."""
    name = f"rbf_{result.options.rbf_export}" if result.rbf is not None else "polynomial"
    out: dict[str, dict[str, float]] = {}
    for split in result.evaluation:
        if split.skipped or name not in split.records:
            continue
        rms = np.asarray(split.records[name].rms, dtype=float)
        out[split.name] = {"accel": float(np.sqrt(np.mean(rms[:3] ** 2))),
                           "gyro": float(np.sqrt(np.mean(rms[3:] ** 2)))}
    return out


def fit_with_lag(frame: pd.DataFrame, opt: FitOptions, provenance: dict[str, Any] | None,
                 progress: Callable[[str], None] | None,
                 fit_plain: Callable[[pd.DataFrame, FitOptions, dict[str, Any] | None, Any], FitResult]
                 ) -> FitResult:
    """The plain fit and the fit at the lag-corrected temperature (tau configured or searched); the one
    exported is the lag-corrected fit when its held-out error is lower, with a `LagReport` either way."""
    plain_opt = replace(opt, thermal_lag_s=None)
    if progress:
        progress("thermal lag: the plain fit (logged temperature)")
    plain = fit_plain(frame, plain_opt, provenance, progress)
    search = None
    if opt.thermal_lag_s == "auto":
        search = search_tau(frame, plain.records, plain_opt, progress)
        tau, source = search.best_tau_s, "auto"
    else:
        tau, source = float(opt.thermal_lag_s), "configured"  # type: ignore[arg-type]
    period = float(np.median(plain.records.row_interval_s)) if len(plain.records) else 1.0
    if tau <= 0:
        plain.thermal_lag = LagReport(0.0, source, False, "the search found no lag", search=search,
                                      sample_period_s=period)
        return plain
    if progress:
        progress(f"thermal lag: the fit at the lag-corrected temperature (tau {tau:.1f} s)")
    lagged = fit_plain(with_temperature(frame, tau), plain_opt, provenance, progress)
    p_rms, l_rms = _exported_rms(plain), _exported_rms(lagged)
    both = {s: {t: {"plain": p_rms[s][t], "lagged": l_rms[s][t]} for t in p_rms[s]} for s in p_rms if s in l_rms}
    ratios = [v["lagged"] / v["plain"] for s in both.values() for v in s.values() if v["plain"] > 0]
    ratio = float(np.mean(ratios)) if ratios else None
    if ratio is None:
        # No held-out split to judge by: the record residual of the search (auto) or the configuration decides.
        used = source == "configured" or (search is not None and min(search.score) < 1.0)
        reason = "no held-out split ran; " + ("configured" if source == "configured" else "it lowers the residual")
    else:
        used = ratio < USE_IF_RATIO_BELOW
        reason = (f"it lowers the held-out error of the exported model by {100 * (1 - ratio):.1f} % on average"
                  if used else f"it does not lower the held-out error (x{ratio:.3f})")
    report = LagReport(tau, source, used, reason, both, ratio, search, period)
    log.info("%s", report.sentence())
    chosen = lagged if used else plain
    chosen.thermal_lag = report
    chosen.options = opt
    return chosen
