"""A model specification (baseline + selected terms) and its per-channel design matrix.

The baseline regressors come from `labrunner.imu.baseline.baseline_design`, the function the
simulator's own error model is written against, so the coefficients fitted here load
straight back into `TriadModel.from_coefficients`. What each term's columns are, and whether a
term moves the baseline's temperature instead, is the term's effect's business.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labrunner.domain import CHANNELS, T_REF_C
from labrunner.imu.baseline import baseline_design
from labrunner.imu.effects import REGISTRY

from .terms import Term, TermContext

BASELINE = "baseline"


@dataclass(frozen=True)
class Selected:
    """A term switched on for some channels with fixed nonlinear parameters."""

    term: str
    theta: tuple[tuple[str, float], ...]
    channels: frozenset[str]

    @property
    def params(self) -> dict[str, float]:
        return dict(self.theta)

    @classmethod
    def make(cls, term: str, theta: dict[str, float], channels: set[str] | frozenset[str] | list[str]) -> Selected:
        return cls(term, tuple(sorted((k, float(v)) for k, v in theta.items())), frozenset(channels))


Spec = tuple[Selected, ...]


def lag_tau(spec: Spec) -> float | None:
    """Time constant of the selected term that moves the baseline's temperature, if any."""
    for s in spec:
        cls = REGISTRY.get(s.term)
        if cls is not None and cls.moves_baseline_temperature:
            return s.params[cls.lag_parameter]
    return None


def _lagged(spec: Spec, channel: str) -> bool:
    """Whether the channel's baseline runs at the lagged temperature in this specification."""
    return any(channel in s.channels and REGISTRY[s.term].moves_baseline_temperature for s in spec)


def replace(spec: Spec, sel: Selected) -> Spec:
    """spec with `sel` added, or substituted for the term of the same name."""
    out = [s for s in spec if s.term != sel.term]
    return tuple(out + [sel])


def without(spec: Spec, term: str) -> Spec:
    return tuple(s for s in spec if s.term != term)


def names(spec: Spec) -> list[str]:
    return [s.term for s in spec]


@dataclass
class Design:
    """Block-level regressors of one channel and where each term's columns sit."""

    x: np.ndarray  # (M, p)
    slices: dict[str, slice]
    parts: list[tuple[tuple, np.ndarray]]  # (key, columns) of the baseline and each term, in order;
    # equal keys are equal columns, so their whitening can be shared between channels and steps


class DesignBuilder:
    """Assembles and caches block-level regressors."""

    def __init__(self, ctx: TermContext, terms: dict[str, Term]) -> None:
        self.ctx = ctx
        self.terms = terms
        self._baseline: dict[tuple[str, float | None], np.ndarray] = {}
        self._columns: dict[tuple, dict[str, np.ndarray]] = {}
        self._baseline_rows: dict[tuple[str, float | None], np.ndarray] = {}

    def baseline(self, channel: str, tau_s: float | None) -> np.ndarray:
        """(M, 16) block means of the baseline regressors (temperature lagged by tau_s if given)."""
        triad = "accel" if channel.startswith("accel") else "gyro"
        key = (triad, tau_s)
        if key not in self._baseline:
            if len(self._baseline) > 48:  # a lag search visits a few dozen time constants
                self._baseline = {k: v for k, v in self._baseline.items() if k[1] is None}
            meas = self.ctx.meas
            ref = meas.force_g if triad == "accel" else meas.rate_dps
            rows = baseline_design(self.ctx.element_temp(tau_s), ref)
            self._baseline[key] = self.ctx.blocks.mean(rows)
        return self._baseline[key]

    def columns(self, term: str, theta: dict[str, float], element_tau: float | None) -> dict[str, np.ndarray]:
        """channel -> (M, q) regressors of a term."""
        uses_temp = self.terms[term].uses_element_temperature
        key = (term, tuple(sorted(theta.items())), element_tau if uses_temp else None)
        if key not in self._columns:
            if len(self._columns) > 64:
                self._columns.clear()
            self._columns[key] = self.terms[term].columns(self.ctx, theta, element_tau if uses_temp else None)
        return self._columns[key]

    def baseline_rows(self, channel: str, tau_s: float | None) -> np.ndarray:
        """(N, 16) row-level baseline regressors (a few kept: the gains reuse them channel by channel)."""
        triad = "accel" if channel.startswith("accel") else "gyro"
        key = (triad, tau_s)
        if key not in self._baseline_rows:
            if len(self._baseline_rows) >= 4:
                self._baseline_rows.pop(next(iter(self._baseline_rows)))
            meas = self.ctx.meas
            ref = meas.force_g if triad == "accel" else meas.rate_dps
            self._baseline_rows[key] = baseline_design(self.ctx.element_temp(tau_s), ref)
        return self._baseline_rows[key]

    def predict_rows(self, spec: Spec, channel: str, betas: np.ndarray, slices: dict[str, slice]) -> np.ndarray:
        """(N, K) row-level model error for K coefficient vectors (K, p) of `design(spec, channel)`."""
        tau = lag_tau(spec)
        lagged = _lagged(spec, channel)
        out = self.baseline_rows(channel, tau if lagged else None) @ betas[:, slices[BASELINE]].T
        for s in spec:
            term = self.terms[s.term]
            if term.moves_baseline_temperature or channel not in s.channels:
                continue
            for k in range(betas.shape[0]):
                out[:, k] += term.predict(self.ctx, s.params, tau, channel, betas[k, slices[s.term]])
        return out

    def design(self, spec: Spec, channel: str) -> Design:
        tau = lag_tau(spec)
        lagged = _lagged(spec, channel)
        triad = "accel" if channel.startswith("accel") else "gyro"
        parts = [self.baseline(channel, tau if lagged else None)]
        key: list = [(BASELINE, triad, tau if lagged else None)]
        slices = {BASELINE: slice(0, parts[0].shape[1])}
        p = parts[0].shape[1]
        for s in spec:
            term = self.terms[s.term]
            if term.moves_baseline_temperature or channel not in s.channels:
                continue
            cols = self.columns(s.term, s.params, tau)[channel]
            parts.append(cols)
            key.append((s.term, s.theta, tau if term.uses_element_temperature else None,
                        channel if term.per_channel_columns else triad))
            slices[s.term] = slice(p, p + cols.shape[1])
            p += cols.shape[1]
        return Design(np.concatenate(parts, axis=1), slices, list(zip(key, parts)))


def design_derivative(temp_c: np.ndarray, reference: np.ndarray, order: int = 1) -> np.ndarray:
    """d/dT (order 1) or d2/dT2 (order 2) of `labrunner.imu.baseline.baseline_design` (N, 16), same layout."""
    tau = np.asarray(temp_c, dtype=float) - T_REF_C
    zero, one = np.zeros_like(tau), np.ones_like(tau)
    if order == 1:
        dp = np.stack([zero, one, 2 * tau, 3 * tau * tau], axis=1)
    else:
        dp = np.stack([zero, zero, 2 * one, 6 * tau], axis=1)
    u = np.asarray(reference, dtype=float)
    return np.concatenate([dp, dp * u[:, 0:1], dp * u[:, 1:2], dp * u[:, 2:3]], axis=1)


def derivative_dot(temp_c: np.ndarray, reference: np.ndarray, coef: np.ndarray, order: int = 1) -> np.ndarray:
    """(N,) `design_derivative(temp_c, reference, order) @ coef` without the (N, 16) matrix: per row,
    the polynomial in (T - 25 degC) whose coefficients are the 16 mixed by the reference."""
    tau = np.asarray(temp_c, dtype=float) - T_REF_C
    c = np.asarray(coef, dtype=float).reshape(4, 4)  # groups [1, u_x, u_y, u_z] x powers 0..3
    eff = c[0][None, :] + np.asarray(reference, dtype=float) @ c[1:]  # (N, 4)
    if order == 1:
        return eff[:, 1] + tau * (2.0 * eff[:, 2] + 3.0 * tau * eff[:, 3])
    return 2.0 * eff[:, 2] + 6.0 * tau * eff[:, 3]


def channel_list(channels: frozenset[str] | set[str]) -> list[str]:
    return sorted(channels, key=CHANNELS.index)
