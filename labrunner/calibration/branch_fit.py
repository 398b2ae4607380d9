"""Calibrating per hysteresis branch (issue 11 item 6): heating and cooling branches apart by a width.

A sensor with hysteresis reads `width / 2` higher on the heating branch than on the cooling branch at
the same temperature (the simulator's `labrunner.imu.effects.hysteresis`, the diagnosis's finding
`hysteresis`). A fit against temperature alone averages the branches and is off by +-width/2 on each.
Per branch, the exported models take the raw outputs less `width / 2 * s`, s the branch state per row:

- the branch state is estimated robustly under sensor jitter and quantisation as the diagnosis judges
  it (`labrunner.discrepancy.temperature`: the row-to-row jitter and the logger's quantum set how much
  the temperature is smoothed): the logged temperature goes through a first-order filter (the thermal
  lag's, `first_order_lag`), its rate of change is compared with a threshold, s = +1 once the filtered
  temperature rises faster than it, -1 once it falls faster, and keeps its value in between (a soak
  keeps the branch the last ramp left). A power-on (a run) and a remount start undecided (s = 0: no
  offset) until the first ramp says which branch: the path the sensor took while it was not logged is
  not known (the diagnosis's guess, through room temperature, put whole soaks on the wrong branch when
  an IMU was power-cycled in the chamber). The filter
  is long enough that its rate noise is an eighth of the threshold, the threshold a quarter of the
  data's ramp rate. All causal, so the C header's state (`branch_state`) gives the same s.
- the widths are fitted jointly with the thermal polynomial (record means; the polynomial fit is linear
  in the data, so two fits give the exact joint least squares), per channel;
- a channel is fitted per branch only when that lowers its held-out record error against the plain fit
  by 15 % on average, no split worse by 5 % (`USE_IF_RATIO_BELOW`, `NO_SPLIT_ABOVE`): splits of the
  records (time blocks, every other interior temperature step) whose widths and polynomials are fitted
  on the training part only.

`BranchReport` says what was done; the exported model dicts carry `branch_state` (the estimator and
the widths) for `labrunner compensate` and the C header.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from labrunner.campaign_csv import OUTPUT_COLUMNS
from labrunner.discrepancy.measurements import temperature_quantum
from labrunner.discrepancy.temperature import is_jittery, temperature_jitter, temperature_rate
from labrunner.domain import CHANNELS
from labrunner.errors import UserError
from labrunner.imu.recursions import first_order_lag

from .compensation import compensate
from .evaluation import time_blocks
from .records import Records, temperature_steps

if TYPE_CHECKING:
    from .fit import FitOptions, FitResult

log = logging.getLogger(__name__)

KIND = "filtered_rate_latch"
THRESHOLD_FRACTION = 0.25  # of the data's ramp rate (90th percentile of |dT/dt| where the temperature moves)
NOISE_MARGIN = 8.0  # the threshold over the filtered rate's noise (jitter and quantisation through the filter)
MIN_THRESHOLD_C_PER_S = 0.02 / 60.0  # when no ramp is logged (soaks joined by gaps)
MIN_TAU_S, MAX_TAU_S = 10.0, 1800.0
# A channel is fitted per branch when its held-out record RMS per branch over the plain fit's is below this
# on average over the splits: a state in the firmware for a material gain only. On 48 h log-like logs
# (tests/discrepancy/log_like.py, seeds 5, 6, 8) the hidden hysteresis gained 25-51 % on its channels, and
# the slow noise alone (a random walk of ~1 mg over a 16 h orientation) 7-13 % on one channel of each log.
USE_IF_RATIO_BELOW = 0.85
# ... and no split worse than this (between temperatures the polynomial's interpolation error can swamp a
# branch offset that time blocks show plainly: 0.74 -> 0.75 mg there, 0.24 -> 0.10 mg on time blocks).
NO_SPLIT_ABOVE = 1.05
MIN_SPLITS = 2  # held-out splits the comparison needs (one alone was decided by its polynomial's luck)
MIN_IDENTIFIED = 0.1  # share of a unit branch offset left in the residual by the polynomial, to fit a width
_RAMP_WINDOW_S = 600.0  # dT/dt over 10 minutes: the ramp rate without the sensor's jitter
_MOVING_C_PER_S = 0.1 / 60.0


@dataclass(frozen=True)
class BranchState:
    """The branch estimator: y = the logged temperature through dy/dt = (x - y)/tau, r = dy/dt between
    rows, s = +1 when r > threshold, -1 when r < -threshold, else the previous s."""

    filter_tau_s: float
    threshold_c_per_s: float
    sample_period_s: float

    def __post_init__(self) -> None:
        for name in ("filter_tau_s", "threshold_c_per_s", "sample_period_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"branch state: {name} must be > 0, not {v!r}")

    def to_dict(self) -> dict[str, Any]:
        return {"kind": KIND, "filter_tau_s": float(self.filter_tau_s),
                "threshold_c_per_s": float(self.threshold_c_per_s), "sample_period_s": float(self.sample_period_s),
                "input": "imu_temp_c",
                "what": "y: imu_temp_c through dy/dt = (imu_temp_c - y) / filter_tau_s, started at the first "
                "temperature; s = +1 when dy/dt > threshold_c_per_s, -1 when dy/dt < -threshold_c_per_s, else "
                "unchanged; s = 0 at power-on (a run) and at a remount"}

    @classmethod
    def from_dict(cls, d: Any) -> BranchState:
        if not isinstance(d, dict) or d.get("kind") != KIND:
            raise ValueError(f"branch_state: expected kind {KIND!r}")
        return cls(float(d["filter_tau_s"]), float(d["threshold_c_per_s"]), float(d["sample_period_s"]))

    def states(self, t_s: np.ndarray, temp_c: np.ndarray, run: np.ndarray | None = None,
               orientation: np.ndarray | None = None) -> np.ndarray:
        """(N,) the branch state of each row in {-1, 0, +1}; rows in time order within each run (a
        campaign frame's are), restarted at each run and each change of orientation."""
        t = np.asarray(t_s, dtype=float)
        x = np.asarray(temp_c, dtype=float)
        out = np.zeros(x.size)
        if x.size == 0:
            return out
        cut = np.zeros(x.size, dtype=bool)
        cut[0] = True
        for labels in (run, orientation):
            if labels is not None:
                lab = np.asarray(labels)
                cut[1:] |= lab[1:] != lab[:-1]
        starts = np.flatnonzero(cut)
        for a, b in zip(starts, np.r_[starts[1:], x.size], strict=True):
            y = first_order_lag(t[a:b], x[a:b], self.filter_tau_s)
            dt = np.diff(t[a:b])
            with np.errstate(divide="ignore", invalid="ignore"):
                r = np.where(dt > 0, np.diff(y) / dt, 0.0)
            step = np.r_[0.0, np.sign(r) * (np.abs(r) > self.threshold_c_per_s)]
            # Latch: each row takes the last nonzero decision at or before it (0 before the first).
            idx = np.where(step != 0, np.arange(step.size), 0)
            np.maximum.accumulate(idx, out=idx)
            out[a:b] = step[idx]
        return out


@dataclass(frozen=True)
class BranchModel:
    """What a model fitted per branch carries: the estimator and the widths (heating minus cooling,
    sensor units, 0 where a triad is not fitted per branch); the model takes y - widths / 2 * s."""

    state: BranchState
    widths: tuple[float, ...]  # (6,) in CHANNELS order

    def to_dict(self) -> dict[str, Any]:
        return {**self.state.to_dict(), "width": {c: float(w) for c, w in zip(CHANNELS, self.widths, strict=True)},
                "applies": "the model's input outputs are y - width / 2 * s (width: heating minus cooling)"}

    @classmethod
    def from_dict(cls, d: Any) -> BranchModel:
        state = BranchState.from_dict(d)
        widths = d.get("width")
        if not isinstance(widths, dict) or set(widths) != set(CHANNELS):
            raise ValueError(f"branch_state: width must give every channel ({', '.join(CHANNELS)})")
        return cls(state, tuple(float(widths[c]) for c in CHANNELS))

    def correct(self, y: np.ndarray, s: np.ndarray) -> np.ndarray:
        """(N, 6) outputs less the branch offset: what the model compensates."""
        return np.asarray(y, dtype=float) - 0.5 * np.asarray(s, dtype=float)[:, None] * np.asarray(self.widths)[None, :]

    def correct_frame(self, frame: pd.DataFrame) -> pd.DataFrame:
        """The frame with its output columns less the branch offset of its rows (a new frame)."""
        s = self.state.states(frame["t_s"].to_numpy(dtype=float), frame["imu_temp_c"].to_numpy(dtype=float),
                              frame["run"].to_numpy(), frame["orientation"].astype(str).to_numpy())
        return frame.assign(**{c: frame[c].to_numpy(dtype=float) - 0.5 * w * s
                               for c, w in zip(OUTPUT_COLUMNS, self.widths, strict=True) if w != 0.0})


def branch_model_from_dict(d: dict[str, Any]) -> BranchModel | None:
    """The branch a model dict carries (`branch_state`), or None."""
    b = d.get("branch_state")
    return None if b is None else BranchModel.from_dict(b)


def estimate_state(frame: pd.DataFrame) -> BranchState:
    """The branch estimator for this data: threshold from its ramp rate, filter from its jitter and quantum
    (the diagnosis's estimates of both)."""
    t = frame["t_s"].to_numpy(dtype=float)
    temp = frame["imu_temp_c"].to_numpy(dtype=float)
    run = frame["run"].to_numpy()
    dt = np.diff(t)
    period = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 1.0
    jitter, reversals = temperature_jitter(t, temp, run)
    q = temperature_quantum(temp) or 0.0
    noise_c = float(np.sqrt((jitter ** 2 if is_jittery(reversals) else 0.0) + q * q / 12.0))
    rate = np.abs(temperature_rate(t, temp, run, window_s=_RAMP_WINDOW_S))
    moving = rate[rate > _MOVING_C_PER_S]
    ramp = float(np.percentile(moving, 90)) if moving.size > 10 else 0.0
    threshold = max(THRESHOLD_FRACTION * ramp, MIN_THRESHOLD_C_PER_S)
    # The filtered rate's noise: white noise of sd `noise_c` through the filter leaves about noise_c / tau.
    tau = float(np.clip(NOISE_MARGIN * noise_c / threshold, max(MIN_TAU_S, 10.0 * period), MAX_TAU_S))
    return BranchState(filter_tau_s=tau, threshold_c_per_s=threshold, sample_period_s=period)


def record_states(records: Records, s: np.ndarray) -> np.ndarray:
    """(R,) the mean branch state over each record's rows."""
    sel = records.row_record >= 0
    lab = records.row_record[sel]
    n = np.bincount(lab, minlength=len(records))
    return np.bincount(lab, weights=s[sel], minlength=len(records)) / np.maximum(n, 1)


def _residual(poly: Any, records: Records, mean: np.ndarray) -> np.ndarray:
    """(R, 6) compensated record means minus the reference."""
    return compensate(poly, mean, records.temp_c).values - records.reference


def _poly(records: Records, opt: FitOptions) -> Any:
    from .fit import fit_models

    return fit_models(records, opt).polynomial


def fit_widths(records: Records, h: np.ndarray, opt: FitOptions) -> tuple[np.ndarray, Any]:
    """(6,) widths and the polynomial fitted jointly with them by least squares over the records. The
    polynomial fit is linear in the record means, so the residual moves linearly with the widths: the
    plain fit and one with a unit width on every channel give each channel's width exactly (the
    compensation's (I + S)^-1 is the same to S's change, ~1e-6)."""
    base = _poly(records, opt)
    e0 = _residual(base, records, records.mean)
    unit_mean = records.mean - 0.5 * h[:, None]
    e1 = _residual(_poly(replace(records, mean=unit_mean), opt), records, unit_mean)
    d = e1 - e0
    den = np.einsum("rc,rc->c", d, d)
    # The share of the branch offset the polynomial cannot take up: below MIN_IDENTIFIED the branch is
    # (nearly) a combination of the thermal and orientation terms on these records, and its width is not
    # fitted (0) rather than blown up by the near-collinearity.
    identified = den / max(float(np.sum((0.5 * h) ** 2)), 1e-300)
    ok = identified > MIN_IDENTIFIED
    w = np.where(ok, -np.einsum("rc,rc->c", e0, d) / np.where(ok, den, 1.0), 0.0)
    corrected = replace(records, mean=records.mean - 0.5 * h[:, None] * w[None, :])
    return w, _poly(corrected, opt)


def _splits(records: Records, opt: FitOptions) -> dict[str, np.ndarray]:
    """Held-out record masks: time blocks, every other interior temperature step. (Not the end steps: in
    extrapolation the polynomial's own error decides, and a width fitted to the middle steps alone doubled
    the held-out error of channels without hysteresis.)"""
    ro = opt.records
    recs = replace(records, step=records.step.copy())  # temperature_steps labels the records in place
    steps = temperature_steps(recs, ro.step_gap_c, ro.max_step_width_c, ro.continuous_gap_c, ro.ramp_bin_c)
    order = np.argsort(steps.temp_c)
    out: dict[str, np.ndarray] = {}
    blocks, _ = time_blocks(records)
    if blocks is not None:
        out["time_blocks"] = blocks
    if len(steps) >= 3:
        out["between_temperatures"] = np.isin(recs.step, order[1:-1:2])
    return {k: v for k, v in out.items() if v.any() and not v.all()}


def _run_offsets(err: np.ndarray, train: np.ndarray, test: np.ndarray, run: np.ndarray) -> np.ndarray:
    """Held-out errors less each run's mean training error (a power-on's own bias, as evaluation's
    time_blocks split removes it)."""
    out = err[test].copy()
    for r in np.unique(run[test]):
        tr = train & (run == r)
        if tr.any():
            out[run[test] == r] -= err[tr].mean(axis=0)
    return out


@dataclass
class BranchReport:
    """What the fit did with the branches: the estimator, the widths fitted on all records, the held-out
    record RMS per split and triad (plain and per branch), and which triads are fitted per branch."""

    state: BranchState
    widths: dict[str, float]
    comparison: Comparison = field(default_factory=lambda: Comparison())
    used_channels: tuple[str, ...] = ()
    reason: str = ""
    rows_heating: int = 0
    rows_cooling: int = 0

    @property
    def used(self) -> bool:
        return bool(self.used_channels)

    @property
    def model(self) -> BranchModel | None:
        """The branch the exported models carry (widths of the channels not used: 0), or None."""
        if not self.used:
            return None
        widths = tuple(self.widths[c] if c in self.used_channels else 0.0 for c in CHANNELS)
        return BranchModel(self.state, widths)

    def sentence(self) -> str:
        gains = ", ".join(f"{c} x{r:.3f}" for c, r in self.comparison.ratio.items())
        verdict = (f"used for {', '.join(self.used_channels)}: the models take the outputs less width/2 x branch"
                   if self.used else "not used")
        return (f"hysteresis per branch (branch from dT/dt of the temperature filtered over "
                f"{self.state.filter_tau_s:.0f} s, threshold {self.state.threshold_c_per_s * 60:.3g} degC/min)"
                f"{'; held-out record RMS per branch / plain ' + gains if gains else ''}: {verdict} ({self.reason})")

    def to_dict(self) -> dict[str, Any]:
        model = self.model
        return {"used": self.used, "used_channels": list(self.used_channels), "reason": self.reason,
                "widths_fitted": self.widths, "heldout_record_rms": self.comparison.heldout,
                "ratio_branch_to_plain": self.comparison.ratio, "worst_split_ratio": self.comparison.worst,
                "rows": {"heating": self.rows_heating, "cooling": self.rows_cooling},
                "branch_state": model.to_dict() if model else None, "estimator": self.state.to_dict()}


@dataclass
class Comparison:
    """The held-out comparison: RMS per split and channel (plain, per branch), and per channel the mean
    over the splits of per branch / plain and the largest over the splits."""

    heldout: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    ratio: dict[str, float] = field(default_factory=dict)
    worst: dict[str, float] = field(default_factory=dict)


def compare(records: Records, h: np.ndarray, opt: FitOptions) -> Comparison:
    """The plain and the per-branch polynomial, both fitted on each split's training records only (the
    widths too), scored on its held-out records."""
    out = Comparison()
    for name, test in _splits(records, opt).items():
        train = ~test
        tr = records.subset(train, with_labels=False)
        try:
            plain = _poly(tr, opt)
            w, branch = fit_widths(tr, h[train], opt)
        except ValueError as exc:  # the training part alone cannot support a polynomial
            log.info("branch fit: split %s skipped (%s)", name, exc)
            continue
        e_plain = _residual(plain, records, records.mean)
        e_branch = _residual(branch, records, records.mean - 0.5 * h[:, None] * w[None, :])
        if name == "time_blocks":
            e_plain = _run_offsets(e_plain, train, test, records.run)
            e_branch = _run_offsets(e_branch, train, test, records.run)
        else:
            e_plain, e_branch = e_plain[test], e_branch[test]
        out.heldout[name] = {c: {"plain": float(np.sqrt(np.mean(e_plain[:, i] ** 2))),
                                 "branch": float(np.sqrt(np.mean(e_branch[:, i] ** 2)))}
                             for i, c in enumerate(CHANNELS)}
    for c in CHANNELS:
        r = [sp[c]["branch"] / sp[c]["plain"] for sp in out.heldout.values() if sp[c]["plain"] > 0]
        if r:
            out.ratio[c] = float(np.mean(r))
            out.worst[c] = float(max(r))
    return out


def fit_with_branches(frame: pd.DataFrame, opt: FitOptions, provenance: dict[str, Any] | None,
                      progress: Callable[[str], None] | None,
                      inner: Callable[[pd.DataFrame, FitOptions, dict[str, Any] | None, Any], FitResult]
                      ) -> FitResult:
    """The plain fit and, where the held-out comparison says it gains, the fit per branch: the outputs less
    width/2 x branch state, refitted by `inner` (the plain fit, or the thermal lag's), with a
    `BranchReport` either way."""
    plain_opt = replace(opt, branch_fit=False)
    if progress:
        progress("hysteresis: the plain fit")
    plain = inner(frame, plain_opt, provenance, progress)
    state = estimate_state(frame)
    s = state.states(frame["t_s"].to_numpy(dtype=float), frame["imu_temp_c"].to_numpy(dtype=float),
                     frame["run"].to_numpy(), frame["orientation"].astype(str).to_numpy())
    records = plain.records
    if records.row_record.size != len(frame):
        raise UserError("hysteresis per branch: the records do not label the frame's rows")
    h = record_states(records, s)
    up, down = int(np.sum(s > 0)), int(np.sum(s < 0))
    poly_opt = replace(plain_opt, rbf_variants=(), rbf_export="", evaluate=False, thermal_lag_s=None)
    report = BranchReport(state, {c: 0.0 for c in CHANNELS}, rows_heating=up, rows_cooling=down)
    if np.sum(h > 0.5) < 2 or np.sum(h < -0.5) < 2:
        report.reason = (f"the records are not on both branches ({int(np.sum(h > 0.5))} heating, "
                         f"{int(np.sum(h < -0.5))} cooling)")
        plain.branch = report
        return plain
    if progress:
        progress("hysteresis: widths per branch, and their held-out gain over the plain fit")
    w, _ = fit_widths(records, h, poly_opt)
    report.widths = {c: float(v) for c, v in zip(CHANNELS, w, strict=True)}
    report.comparison = cmp = compare(records, h, poly_opt)
    if len(cmp.heldout) < MIN_SPLITS:
        report.reason = (f"{len(cmp.heldout)} held-out split(s) could be fitted "
                         f"({', '.join(cmp.heldout) or 'none'}), {MIN_SPLITS} are needed to judge the gain: not used")
        plain.branch = report
        return plain
    used = [c for c in CHANNELS if cmp.ratio.get(c, 1.0) < USE_IF_RATIO_BELOW and cmp.worst[c] < NO_SPLIT_ABOVE]
    report.used_channels = tuple(used)
    report.reason = (f"{', '.join(used)}: the held-out record error lower by "
                     + ", ".join(f"{100 * (1 - cmp.ratio[c]):.1f} %" for c in used) + " on average over the splits"
                     if used else f"no channel's held-out record error is below x{USE_IF_RATIO_BELOW} of the plain "
                     f"fit's on average with no split above x{NO_SPLIT_ABOVE}")
    log.info("%s", report.sentence())
    model = report.model
    if model is None:
        plain.branch = report
        return plain
    if progress:
        progress("hysteresis: the fit per branch")
    chosen = inner(model.correct_frame(frame), plain_opt, provenance, progress)
    chosen.branch = report
    chosen.options = opt  # chosen.frame stays the corrected rows: the figures compensate what the models take
    return chosen


def c_section(p: str, branch: BranchModel, num: Callable[[float], str]) -> list[str]:
    """The C header's branch state and output correction (`num`: the header's number format). The filter
    step is the thermal lag's (exact first-order hold); its change dy over the sample against threshold x dt
    sets the branch, as `BranchState.states` does."""
    st = branch.state
    alpha = float(np.exp(-st.sample_period_s / st.filter_tau_s))
    beta = float(-np.expm1(-st.sample_period_s / st.filter_tau_s) * st.filter_tau_s / st.sample_period_s)
    widths = ", ".join(num(w) for w in branch.widths)
    return [
        "/* ---- hysteresis branch: heating and cooling branches apart by a width ----",
        " * s = +1 on the heating branch, -1 on the cooling branch, 0 undecided (from power-on to the first ramp):",
        f" * the temperature through a first-order filter of tau = {st.filter_tau_s:g} s, s set when its rate passes",
        f" * +-{st.threshold_c_per_s * 60.0:g} degC/min and kept in between. Call {p}branch_init at power-on, then",
        f" * {p}branch_update with every sample's temperature (every {st.sample_period_s:g} s; {p}branch_update_dt",
        f" * for another interval), and pass the y that {p}branch_correct returns to the compensation functions. */",
        f"#define {p.upper()}BRANCH 1",
        f"static const lr_real {p}branch_tau_s = {num(st.filter_tau_s)};",
        f"static const lr_real {p}branch_period_s = {num(st.sample_period_s)};",
        f"static const lr_real {p}branch_alpha = {num(alpha)};  /* exp(-period / tau) */",
        f"static const lr_real {p}branch_beta = {num(beta)};  /* (1 - alpha) tau / period */",
        f"static const lr_real {p}branch_threshold_c_per_s = {num(st.threshold_c_per_s)};",
        f"static const lr_real {p}branch_width[6] = {{{widths}}};  /* heating minus cooling */",
        f"typedef struct {{ lr_real y, x_prev; int s; }} {p}branch;",
        "",
        f"static inline void {p}branch_init({p}branch *b, lr_real temp_c)",
        "{",
        "    b->y = temp_c;",
        "    b->x_prev = temp_c;",
        "    b->s = 0;",
        "}",
        "",
        f"static inline int {p}branch_step({p}branch *b, lr_real temp_c, lr_real dt_s, lr_real alpha, lr_real beta)",
        "{",
        "    /* y' - y of the filter step y' = x + alpha (y - x_prev) - beta (x - x_prev), in differences */",
        "    lr_real dy = (1 - beta) * (temp_c - b->x_prev) - (1 - alpha) * (b->y - b->x_prev);",
        "    b->y += dy;",
        "    b->x_prev = temp_c;",
        f"    if (dt_s > 0 && dy > {p}branch_threshold_c_per_s * dt_s) b->s = 1;",
        f"    else if (dt_s > 0 && dy < -{p}branch_threshold_c_per_s * dt_s) b->s = -1;",
        "    return b->s;",
        "}",
        "",
        f"static inline int {p}branch_update({p}branch *b, lr_real temp_c)",
        "{",
        f"    return {p}branch_step(b, temp_c, {p}branch_period_s, {p}branch_alpha, {p}branch_beta);",
        "}",
        "",
        f"static inline int {p}branch_update_dt({p}branch *b, lr_real temp_c, lr_real dt_s)",
        "{",
        "    lr_real x, em1;",
        f"    if (dt_s <= 0) return {p}branch_step(b, temp_c, 0, 1, 1);",
        f"    x = dt_s / {p}branch_tau_s;",
        "    em1 = -LR_EXPM1(-x);  /* 1 - alpha */",
        f"    return {p}branch_step(b, temp_c, dt_s, 1 - em1, em1 / x);",
        "}",
        "",
        f"static inline void {p}branch_correct(const lr_real y[6], int s, lr_real yc[6])",
        "{",
        "    int k;",
        f"    for (k = 0; k < 6; ++k) yc[k] = y[k] - (lr_real)0.5 * {p}branch_width[k] * (lr_real)s;",
        "}",
    ]
