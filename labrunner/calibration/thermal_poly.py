"""Thermal polynomial model (paper Eq. 4-5): bias, scale factor and misalignment as polynomials in T.

Each error term of a triad is p(T) = sum_k c_k (T - t_ref)^k (default t_ref 25 C, third
order). Two ways to fit it:

* ``two_stage`` (the paper): six-position calibration at each temperature step, then a
  polynomial through the per-step estimates of each term.
* ``joint`` (default, better): all coefficients of the triad fitted at once to every
  record mean, each record at its own IMU temperature. Orientations are recorded hours
  apart at slightly different IMU temperatures (self-heating, soak tolerance), and the
  two-stage method folds those differences into the step estimates: with the paper's
  accelerometer (bias slope ~3.7 mg/C) a 0.1 C difference between up and down biases
  the scale factor by ~0.2 mg, far above its noise. The joint fit has no such bias and
  propagates the record noise directly into the coefficient covariance.

The order can be fixed or chosen by leave-one-temperature-step-out cross-validation
(interior steps only, so the criterion measures interpolation). The model keeps the
temperature range of its data; compensation flags samples outside it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .lsq import gauge_lstsq, weighted_lstsq
from .records import Records, TemperatureSteps
from .six_position import StepCalibration, _nan_to_none, is_rotating
from .triads import AXES, TRIAD_SLICE, describe_missing


@dataclass
class TriadPoly:
    """Polynomial thermal model of one triad: b(T) and S(T), coefficients of (T - t_ref)^k."""

    triad: str
    order: int
    t_ref_c: float
    bias: np.ndarray  # (3, order+1); 0 where not fitted
    scale: np.ndarray  # (3, 3, order+1)
    bias_std: np.ndarray  # (3, order+1); nan where unknown
    scale_std: np.ndarray  # (3, 3, order+1)
    t_min_c: float
    t_max_c: float
    method: str = "joint"
    fitted: np.ndarray = field(default_factory=lambda: np.ones((3, 4), dtype=bool))  # (channel, block)
    not_fitted: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    # Terms fitted only in combination (bias with scale factor and misalignment when no axis is seen
    # both up and down): what was combined and for which use the model is valid, in sentences.
    combined: list[str] = field(default_factory=list)
    residual_rms: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # record-mean residuals
    cv_scores: dict[int, float] = field(default_factory=dict)  # order -> CV mean-square error, if chosen by CV
    # (3, 4(order+1), 4(order+1)): covariance of each channel's `coefficients()`, nan where unknown; for the
    # ±1 sigma band of a fitted term (figures). Not in the model JSON: compensation does not need it.
    coef_cov: np.ndarray | None = field(default=None, repr=False)

    def powers(self, temp_c: np.ndarray) -> np.ndarray:
        tau = np.asarray(temp_c, dtype=float) - self.t_ref_c
        return tau[..., None] ** np.arange(self.order + 1)

    def bias_at(self, temp_c: np.ndarray) -> np.ndarray:
        """(N, 3) bias."""
        return self.powers(temp_c) @ self.bias.T

    def scale_at(self, temp_c: np.ndarray) -> np.ndarray:
        """(N, 3, 3) S(T)."""
        return np.einsum("nk,ijk->nij", self.powers(np.atleast_1d(temp_c)), self.scale)

    def coefficients(self) -> np.ndarray:
        """(3, 4*(order+1)) per channel [bias c0..cn, S_i0 c0..cn, S_i1 ..., S_i2 ...]."""
        return np.concatenate([self.bias, self.scale[:, 0], self.scale[:, 1], self.scale[:, 2]], axis=1)

    def coefficient_std(self) -> np.ndarray:
        return np.concatenate([self.bias_std, self.scale_std[:, 0], self.scale_std[:, 1], self.scale_std[:, 2]],
                              axis=1)

    def to_dict(self) -> dict[str, Any]:
        return {
            "triad": self.triad, "method": self.method, "order": self.order, "t_ref_c": self.t_ref_c,
            "basis": "(T - t_ref_c)**k, k = 0..order",
            "temperature_range_c": [self.t_min_c, self.t_max_c],
            "bias": self.bias.tolist(), "bias_std": _nan_to_none(self.bias_std),
            "scale": self.scale.tolist(), "scale_std": _nan_to_none(self.scale_std),
            "fitted": self.fitted.tolist(), "not_fitted": self.not_fitted, "notes": self.notes,
            "combined": self.combined, "residual_rms": _nan_to_none(self.residual_rms),
            "cv_scores": {str(k): v for k, v in self.cv_scores.items()},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TriadPoly:
        def arr(v: Any) -> np.ndarray:
            return np.array(v, dtype=float)  # None -> nan

        lo, hi = d["temperature_range_c"]
        return cls(
            triad=d["triad"], order=int(d["order"]), t_ref_c=float(d["t_ref_c"]), bias=arr(d["bias"]),
            scale=arr(d["scale"]), bias_std=arr(d["bias_std"]), scale_std=arr(d["scale_std"]),
            t_min_c=float(lo), t_max_c=float(hi), method=d.get("method", "joint"),
            fitted=np.array(d.get("fitted", np.ones((3, 4))), dtype=bool), not_fitted=list(d.get("not_fitted", [])),
            notes=list(d.get("notes", [])), combined=list(d.get("combined", [])),
            residual_rms=arr(d.get("residual_rms", [np.nan] * 3)),
            cv_scores={int(k): float(v) for k, v in (d.get("cv_scores") or {}).items()},
        )


def _temp_scale(temp: np.ndarray, t_ref: float) -> float:
    return float(max(np.max(np.abs(temp - t_ref)), 1.0)) if temp.size else 1.0


def joint_design(temp_c: np.ndarray, reference: np.ndarray, order: int, t_ref: float, t_scale: float) -> np.ndarray:
    """(N, 4(order+1)) design of one channel's error: [P, P u0, P u1, P u2], P = powers of (T-t_ref)/t_scale."""
    x = (np.asarray(temp_c, dtype=float) - t_ref) / t_scale
    p = x[:, None] ** np.arange(order + 1)
    u = np.asarray(reference, dtype=float)
    return np.concatenate([p, p * u[:, 0:1], p * u[:, 1:2], p * u[:, 2:3]], axis=1)


def _unpack(coef: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """(3, 4(n+1)) -> bias (3, n+1), scale (3, 3, n+1)."""
    m = order + 1
    return coef[:, :m], np.stack([coef[:, m * (1 + j): m * (2 + j)] for j in range(3)], axis=1)


def run_offset_design(run: np.ndarray) -> np.ndarray:
    """(N, R-1) effect coding of R runs (power-ons): run j's column is 1 in run j, -1 in the last run. The
    offsets sum to zero over the runs, so the bias constant is the mean level of the runs."""
    runs = np.unique(run)
    return np.column_stack([(run == r).astype(float) - (run == runs[-1]) for r in runs[:-1]]) if runs.size > 1 \
        else np.zeros((run.size, 0))


def fit_joint(records: Records, triad: str, order: int, t_ref_c: float = 25.0,
              run_offsets: bool = False) -> TriadPoly:
    """One-stage fit of b(T), S(T) to all record means of a triad. With `run_offsets`, each run
    (power-on) has its own offset, a nuisance the thermal terms are fitted around (a turn-on bias)."""
    sl = TRIAD_SLICE[triad]
    u = records.reference[:, sl]
    temp = records.temp_c
    t_scale = _temp_scale(temp, t_ref_c)
    x = joint_design(temp, u, order, t_ref_c, t_scale)
    target = records.mean[:, sl] - u
    n_par = x.shape[1]
    if run_offsets:
        x = np.hstack([x, run_offset_design(records.run)])
    fit = weighted_lstsq(x, target, records.duration_s, known_var=records.sem[:, sl] ** 2)
    if run_offsets:  # drop the nuisance parameters: the model is the thermal part
        fit.coef, fit.identifiable = fit.coef[:n_par], fit.identifiable[:n_par]
        fit.cov = fit.cov[:, :n_par, :n_par]
        x = x[:, :n_par]
    ident = fit.identifiable.reshape(4, order + 1)
    raw = np.where(np.isfinite(fit.coef), fit.coef, 0.0)
    combined: list[str] = []
    # Blocks not one of whose temperature coefficients the data determine.
    whole: np.ndarray = np.asarray(~ident.any(axis=1))
    if whole[0] and whole[1:].any() and not (ident.any(axis=1) & ~ident.all(axis=1)).any():
        # Bias and S confounded (no axis seen both up and down): fit what the orientations do determine,
        # each axis's output in each seen orientation as a function of T, common part in the bias. S(T) is
        # held to first order (scale factor and misalignment change smoothly with temperature), so the
        # bias's higher powers are common to the orientations: one orientation's data inform the others
        # where its own temperatures have holes.
        power = np.tile(np.arange(order + 1), 4)
        block = np.repeat(np.arange(4), order + 1)
        keep = (block == 0) | (power <= 1)
        raw = np.zeros_like(raw)
        raw[keep] = gauge_lstsq(x[:, keep], target, records.duration_s, preferred=block[keep] == 0)
        combined.append(_combined_sentence(triad, records, order, t_ref_c, whole))
    # Back from the scaled variable to (T - t_ref)^k.
    conv = np.tile(t_scale ** -np.arange(order + 1.0), 4)
    coef = raw.T * conv  # (3, p)
    std = fit.std.T * conv
    coef_cov = fit.cov * conv[None, :, None] * conv[None, None, :]
    bias, scale = _unpack(coef, order)
    bias_std, scale_std = _unpack(std, order)
    fitted = np.tile(ident.any(axis=1), (3, 1))
    notes: list[str] = []
    partial = ident.any(axis=1) & ~ident.all(axis=1)
    if partial.any():
        blocks = ", ".join(_block_label(int(b)) for b in np.flatnonzero(partial))
        notes.append(f"{triad}: some temperature coefficients of {blocks}"
                     " cannot be fitted from these temperatures; they are set to 0")
    missing = [(c, b) for c in range(3) for b in range(4) if not ident[b].any()]
    not_fitted = [describe_missing(triad, missing, records.orientation, is_rotating(records))] if missing else []
    if combined and not_fitted:  # separately, that is: what the orientations determine is in the model
        not_fitted[0] += "; they are fitted in combination instead (see 'combined')"
    w = records.duration_s
    resid = target - x @ raw if combined else fit.residual
    rms = np.sqrt(np.sum(w[:, None] * resid ** 2, axis=0) / np.sum(w)) if len(records) else np.full(3, np.nan)
    return TriadPoly(
        triad=triad, order=order, t_ref_c=t_ref_c, bias=bias, scale=scale, bias_std=bias_std, scale_std=scale_std,
        t_min_c=float(temp.min()), t_max_c=float(temp.max()), method="joint", fitted=fitted, not_fitted=not_fitted,
        notes=notes, combined=combined, residual_rms=rms, coef_cov=coef_cov,
    )


def _combined_sentence(triad: str, records: Records, order: int, t_ref_c: float, whole: np.ndarray) -> str:
    from .triads import ORIENTATIONS

    seen = ", ".join(ORIENTATIONS[i] for i in sorted(set(records.orientation.tolist())))
    what = "bias" + ("" if not whole[1:].all() else " with scale factor and misalignment")
    runs = len(set(records.run.tolist()))
    return (f"{triad}: {what} fitted in combination, as each axis's output in each orientation seen ({seen}) as a "
            f"polynomial of order {order} in (T - {t_ref_c:g} C): the bias is the part common to the orientations, "
            "S(T) (at most linear in T) only their differences. Valid for compensating the IMU in (or near) those "
            "orientations, e.g. "
            f"static or slow data in the mounting it was calibrated in; not a separation of bias from scale factor "
            f"(no axis was seen both up and down)"
            + (f"; each of the {runs} runs (power-ons) keeps its own turn-on bias in its orientation's level"
               if runs > 1 else ""))


def _block_label(b: int) -> str:
    return "bias" if b == 0 else f"S[:, {AXES[b - 1]}]"


def fit_two_stage(steps_cal: list[StepCalibration], order: int, t_ref_c: float = 25.0,
                  t_min_c: float | None = None, t_max_c: float | None = None) -> TriadPoly:
    """The paper's second stage: a polynomial through each term's per-step six-position estimates.

    Coefficients are ordinary least squares (as the paper); their covariance is propagated
    from the step uncertainties and inflated by the reduced chi-square when the points
    scatter more than their uncertainties say.
    """
    triad = steps_cal[0].triad
    temps = np.array([s.temp_c for s in steps_cal])
    vals = np.stack([s.params() for s in steps_cal])  # (K, 3, 4)
    sds = np.stack([s.params_std() for s in steps_cal])
    t_scale = _temp_scale(temps, t_ref_c)
    m = order + 1
    bias = np.zeros((3, m))
    scale = np.zeros((3, 3, m))
    bias_std = np.full((3, m), np.nan)
    scale_std = np.full((3, 3, m), np.nan)
    fitted = np.zeros((3, 4), dtype=bool)
    coef_cov = np.full((3, 4 * m, 4 * m), np.nan)  # terms are fitted separately: only the diagonal blocks
    conv = t_scale ** -np.arange(float(m))
    for c in range(3):
        for b in range(4):
            ok = np.isfinite(vals[:, c, b])
            if ok.sum() < m:
                continue
            x = (((temps[ok] - t_ref_c) / t_scale)[:, None]) ** np.arange(m)
            coef, *_ = np.linalg.lstsq(x, vals[ok, c, b], rcond=None)
            pinv = np.linalg.pinv(x)
            var = sds[ok, c, b] ** 2
            sd = np.full(m, np.nan)
            if np.all(np.isfinite(var)):
                cov = (pinv * var) @ pinv.T
                dof = int(ok.sum()) - m
                if dof > 0 and np.all(var > 0):
                    chi2 = float(np.sum((vals[ok, c, b] - x @ coef) ** 2 / var)) / dof
                    cov *= max(1.0, chi2)
                sd = np.sqrt(np.clip(np.diag(cov), 0, None))
                coef_cov[c, b * m:(b + 1) * m, b * m:(b + 1) * m] = cov * np.outer(conv, conv)
            fitted[c, b] = True
            target = bias[c] if b == 0 else scale[c, b - 1]
            target[:] = coef * conv
            (bias_std[c] if b == 0 else scale_std[c, b - 1])[:] = sd * conv
    not_fitted = sorted({s for st in steps_cal for s in st.not_fitted})
    lo = float(temps.min()) if t_min_c is None else t_min_c
    hi = float(temps.max()) if t_max_c is None else t_max_c
    return TriadPoly(triad=triad, order=order, t_ref_c=t_ref_c, bias=bias, scale=scale, bias_std=bias_std,
                     scale_std=scale_std, t_min_c=lo, t_max_c=hi, method="two_stage", fitted=fitted,
                     not_fitted=not_fitted, coef_cov=coef_cov)


def record_prediction(model: TriadPoly, records: Records) -> np.ndarray:
    """(R, 3) predicted mean output y = (I + S) u + b of the records under the model."""
    u = records.reference[:, TRIAD_SLICE[model.triad]]
    s = model.scale_at(records.temp_c)
    return u + np.einsum("nij,nj->ni", s, u) + model.bias_at(records.temp_c)


def max_order(n_steps: int, requested: int) -> int:
    """Highest order the temperature steps support (a polynomial needs order+1 distinct points)."""
    return max(0, min(requested, n_steps - 1))


def cv_order(records: Records, steps: TemperatureSteps, triad: str, max_order_: int, method: str,
             t_ref_c: float = 25.0) -> tuple[int, dict[int, float]]:
    """Order with the least leave-one-interior-step-out prediction error of the record means.

    Errors are normalised per channel by the record noise so channels weigh alike. Falls
    back to the highest supported order when there are too few steps to cross-validate.
    """
    from .six_position import calibrate_steps

    k = len(steps)
    interior = np.argsort(steps.temp_c)[1:-1]
    top = min(max_order_, k - 2)
    if interior.size == 0 or top < 0:
        return max_order(k, max_order_), {}
    sl = TRIAD_SLICE[triad]
    noise = np.nanmedian(records.sem[:, sl], axis=0)
    noise = np.where(np.isfinite(noise) & (noise > 0), noise, 1.0)
    per_step = calibrate_steps(records, steps)[triad] if method == "two_stage" else []
    scores: dict[int, float] = {}
    for order in range(top + 1):
        total, weight = 0.0, 0.0
        for hold in interior:
            test = records.subset(records.step == hold, with_labels=False)
            if method == "joint":
                model = fit_joint(records.subset(records.step != hold, with_labels=False), triad, order, t_ref_c)
            else:
                model = fit_two_stage([c for i, c in enumerate(per_step) if i != hold], order, t_ref_c)
            err = (record_prediction(model, test) - test.mean[:, sl]) / noise
            w = test.duration_s
            total += float(np.sum(w[:, None] * err ** 2))
            weight += float(np.sum(w)) * 3
        scores[order] = total / weight
    best = min(scores, key=scores.__getitem__)
    return best, scores


@dataclass
class PolyModel:
    """Polynomial thermal model of both triads."""

    accel: TriadPoly
    gyro: TriadPoly

    def triads(self) -> dict[str, TriadPoly]:
        return {"accel": self.accel, "gyro": self.gyro}

    @property
    def t_min_c(self) -> float:
        return min(self.accel.t_min_c, self.gyro.t_min_c)

    @property
    def t_max_c(self) -> float:
        return max(self.accel.t_max_c, self.gyro.t_max_c)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "polynomial", "accel": self.accel.to_dict(), "gyro": self.gyro.to_dict()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PolyModel:
        return cls(accel=TriadPoly.from_dict(d["accel"]), gyro=TriadPoly.from_dict(d["gyro"]))
