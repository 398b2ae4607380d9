"""The noise as a finding: Allan deviation of the residuals, the simulator's noise model fitted to it.

The residual (measured minus the extended model's deterministic error) is what the simulator
has to reproduce with its noise model. Its overlapping Allan deviation (allantools) at octaves
of tau, from the row spacing to a tenth of the longest stretch logged without a gap, is fitted
by the noise model of `labrunner.imu` -- white noise (`TriadModel.noise_density`), bias
instability (`bias_instability`), rate random walk (`bias_random_walk`) -- whose Allan variance is
linear in the squares of its parameters:

    AVAR(tau) = N^2 / (2 tau)  +  B^2 F(tau)  +  K^2 tau / 3

with N the simulator's one-sided white-noise density (a row that averages dt of samples of
density N has RMS N / sqrt(2 dt), so the Allan deviation is N / sqrt(2 tau): the IEEE angle
random walk coefficient is N / sqrt(2)), F the exact Allan variance of the simulator's bias
instability at B = 1, K the random walk per sqrt(s). Fitted by non-negative least squares in
relative terms (every octave counts alike). The gain is the mismatch between the measured Allan
deviation and that of the simulator's noise, before (white noise only) and after (the fitted
model): the simulator is run on the same rows and the same estimator applied to what it makes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import allantools
import numpy as np
from scipy.optimize import nnls

from labrunner.domain import CHANNELS
from labrunner.imu.baseline import baseline_design
from labrunner.imu.effects.bias_instability import allan_variance as instability_avar
from labrunner.imu.effects.bias_instability import unit_wander

from .measurements import Measurements

log = logging.getLogger(__name__)

_MIN_ROWS = 256  # a stretch shorter than this says little about the noise
TARGET = 0.20  # the simulator's Allan deviation within 20 % of the measured one at every octave


@dataclass
class AllanCurve:
    tau_s: np.ndarray  # (T,)
    adev: np.ndarray  # (T, 6), sensor units
    terms: np.ndarray  # (T,) number of Allan terms behind each tau (all stretches)


@dataclass
class NoiseFit:
    white: dict[str, float]  # one-sided density, units/sqrt(Hz), as TriadModel.noise_density
    bias_instability: dict[str, float]  # B, units (Allan floor 0.664 B)
    rate_random_walk: dict[str, float]  # K, units/sqrt(s)
    measured: AllanCurve
    before: AllanCurve  # the simulator's noise as it was (white noise only)
    after: AllanCurve  # the fitted noise model
    mismatch_before: dict[str, float] = field(default_factory=dict)  # max over octaves |sim/meas - 1|
    mismatch_after: dict[str, float] = field(default_factory=dict)


def stretches(meas: Measurements) -> list[slice]:
    """Row ranges logged without a gap at the log's typical spacing, within one power-on."""
    t = meas.t_s
    dt = meas.row_dt_s
    step = np.diff(t)
    cut = np.r_[True, (np.abs(step - dt) > 0.01 * dt) | (meas.run[1:] != meas.run[:-1])]
    starts = np.flatnonzero(cut)
    ends = np.r_[starts[1:], t.size]
    return [slice(int(s), int(e)) for s, e in zip(starts, ends) if e - s >= _MIN_ROWS]


def octave_taus(dt: float, longest_s: float) -> np.ndarray:
    """dt, 2 dt, 4 dt, ... up to a tenth of the longest stretch."""
    k = int(np.floor(np.log2(max(longest_s / 10.0 / dt, 1.0))))
    return dt * 2.0 ** np.arange(k + 1)


def allan_curve(values: np.ndarray, parts: list[slice], dt: float, taus: np.ndarray) -> AllanCurve:
    """Overlapping Allan deviation of each column, pooled over the stretches (variances weighted
    by their number of terms)."""
    num = np.zeros((taus.size, values.shape[1]))
    terms = np.zeros(taus.size)
    for part in parts:
        rows = part.stop - part.start
        usable = taus[taus <= (rows - 1) * dt / 2.0]
        if usable.size == 0:
            continue
        for i in range(values.shape[1]):
            got_tau, adev, _, ns = allantools.oadev(values[part, i], rate=1.0 / dt, data_type="freq",
                                                   taus=usable)
            idx = np.searchsorted(taus, got_tau)
            num[idx, i] += ns * adev * adev
            if i == 0:
                terms[idx] += ns
    ok = terms > 0
    adev = np.sqrt(num[ok] / terms[ok, None])
    return AllanCurve(taus[ok], adev, terms[ok])


def _design(meas: Measurements, triad: int) -> np.ndarray:
    """(N, 16) the baseline's row regressors of a triad: what the deterministic fit takes out."""
    return baseline_design(meas.temp_c, meas.force_g if triad == 0 else meas.rate_dps)


def _project(values: np.ndarray, design: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """values minus their least-squares fit by the design (`inverse`: pinv of its Gram): what the
    analysis leaves of a noise."""
    return values - design @ (inverse @ (design.T @ values))


def unit_noises(meas: Measurements, rng: np.random.Generator) -> np.ndarray:
    """(N, 3) one draw each of the simulator's white noise (density 1), bias instability (B = 1) and
    random walk (K = 1) on these rows."""
    assert meas.row_spacing_s is not None
    t = meas.t_s
    white = rng.standard_normal(t.size) / np.sqrt(2.0 * meas.row_spacing_s)
    wander, _ = unit_wander(t, None, None, rng, width=1)
    dt = np.maximum(np.diff(t, prepend=t[:1]), 0.0)
    walk = np.cumsum(rng.standard_normal(t.size) * np.sqrt(dt))
    return np.column_stack([white, wander[:, 0], walk])


def analytic_basis(taus: np.ndarray, dt: float) -> np.ndarray:
    """(T, 3) Allan variance of the simulator's unit white noise (density 1), bias instability (B = 1)
    and random walk (K = 1) in rows dt apart: N^2 / (2 tau), B^2 F(tau), K^2 (tau / 3 + dt^2 / (6 tau))."""
    return np.column_stack([1.0 / (2.0 * taus), instability_avar(taus, dt), taus / 3.0 + dt * dt / (6.0 * taus)])


def bases(meas: Measurements, parts: list[slice], taus: np.ndarray, draws: int = 1) -> dict[int, np.ndarray]:
    """Per triad, (T, 3) the Allan variance each unit noise shows after the same deterministic fit as
    the data: the analytic curve times the share the fit leaves, measured by simulating the noise and
    fitting it away (the ratio of the Allan variances after and before the fit, on the same draws, so
    the draw's own scatter cancels)."""
    rng = np.random.default_rng(0x41A)
    exact = analytic_basis(taus, meas.row_dt_s)
    out = {}
    for triad in (0, 1):
        design = _design(meas, triad)
        scale = np.sqrt(np.maximum(np.einsum("np,np->p", design, design), 1e-300))
        design = design / scale  # unit columns: the Gram's pseudo-inverse is then well conditioned
        inverse = np.linalg.pinv(design.T @ design, rcond=1e-10, hermitian=True)
        share = np.zeros((taus.size, 3))
        for _ in range(draws):
            noise = unit_noises(meas, rng)
            raw = allan_curve(noise, parts, meas.row_dt_s, taus).adev
            kept = allan_curve(_project(noise, design, inverse), parts, meas.row_dt_s, taus).adev
            share += (kept / raw) ** 2
        out[triad] = exact * np.minimum(share / draws, 1.0)
    return out


def fit_parameters(curve: AllanCurve, basis: dict[int, np.ndarray]) -> np.ndarray:
    """(6, 3) N, B, K per channel, by non-negative least squares on the relative Allan variance."""
    out = np.zeros((curve.adev.shape[1], 3))
    for i in range(curve.adev.shape[1]):
        meas = curve.adev[:, i] ** 2
        a = basis[0 if i < 3 else 1][: meas.size]
        if not np.all(np.isfinite(meas)) or np.any(meas <= 0):
            continue
        # Relative terms, each octave weighed by how well it is measured: an Allan variance at tau
        # rests on about T / tau independent differences, so its relative error grows as sqrt(tau).
        w = 1.0 / np.sqrt(curve.tau_s / curve.tau_s[0])
        coef, _ = nnls(a * (w / meas)[:, None], w)
        out[i] = np.sqrt(coef)
    return out


def model_curve(params: np.ndarray, basis: dict[int, np.ndarray], taus: np.ndarray) -> AllanCurve:
    """The simulator's Allan deviation after the fit, for parameters (6, 3)."""
    adev = np.column_stack([np.sqrt(basis[0 if i < 3 else 1][: taus.size] @ (params[i] ** 2))
                            for i in range(params.shape[0])])
    return AllanCurve(taus, adev, np.zeros(taus.size))


def mismatch(sim: AllanCurve, measured: AllanCurve) -> dict[str, float]:
    """Per channel, the largest relative departure of the simulated Allan deviation over the octaves."""
    ratio = sim.adev / measured.adev
    return {c: float(np.max(np.abs(ratio[:, i] - 1.0))) for i, c in enumerate(CHANNELS)}


def fit_noise(meas: Measurements, residual: np.ndarray, white_before: np.ndarray) -> NoiseFit | None:
    """The noise finding's numbers (`white_before`: the simulator's white densities as they were,
    per channel), or None when no stretch is long enough."""
    parts = stretches(meas)
    if not parts:
        return None
    longest = max(p.stop - p.start for p in parts) * meas.row_dt_s
    taus = octave_taus(meas.row_dt_s, longest)
    measured = allan_curve(residual, parts, meas.row_dt_s, taus)
    if measured.tau_s.size < 3:
        return None
    basis = bases(meas, parts, measured.tau_s)
    params = fit_parameters(measured, basis)
    before_params = np.column_stack([white_before, np.zeros(6), np.zeros(6)])
    before = model_curve(before_params, basis, measured.tau_s)
    after = model_curve(params, basis, measured.tau_s)
    fit = NoiseFit(white={c: float(params[i, 0]) for i, c in enumerate(CHANNELS)},
                   bias_instability={c: float(params[i, 1]) for i, c in enumerate(CHANNELS)},
                   rate_random_walk={c: float(params[i, 2]) for i, c in enumerate(CHANNELS)},
                   measured=measured, before=before, after=after)
    fit.mismatch_before = mismatch(before, measured)
    fit.mismatch_after = mismatch(after, measured)
    return fit
