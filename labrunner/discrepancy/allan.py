"""The noise as a finding: Allan deviation of the residuals, the simulator's noise model fitted to it.

The residual (measured minus the extended model's deterministic error) is what the simulator
has to reproduce with its noise model. Its overlapping Allan deviation (allantools) at octaves
of tau, from the row spacing to a tenth of the longest record (a stretch logged without a gap, in
one power-on and one orientation), is fitted
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
The measured curve's own 68 % interval (allantools: Greenhall's equivalent degrees of freedom for
the noise the fit says dominates each octave) is reported with it: at the top octaves of a record
it is wider than the 20 % target, and `excess_*` judges the mismatch against the wider of the two.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field

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
    # The measured curve's 68 % interval (None for a simulated curve), sensor units, (T, 6) each.
    low: np.ndarray | None = None
    high: np.ndarray | None = None


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
    # The largest departure beyond the allowance of its octave: the target or, where wider, the
    # measured curve's 68 % interval on that side (0: every octave within one of them).
    excess_before: dict[str, float] = field(default_factory=dict)
    excess_after: dict[str, float] = field(default_factory=dict)


def stretches(meas: Measurements) -> list[slice]:
    """The records: row ranges logged without a gap at the log's typical spacing, within one
    power-on and one orientation. A remount ends a record even without a gap: the accelerometer's
    baseline is fitted per orientation, so its residual steps there by however far the slow noise
    has wandered, a step of the fit, not of the noise (across them a 48 h log's Allan deviation
    came out 20 % above the noise hidden in it at 256-2048 s)."""
    t = meas.t_s
    dt = meas.row_dt_s
    step = np.diff(t)
    cut = np.r_[True, (np.abs(step - dt) > 0.01 * dt) | (meas.run[1:] != meas.run[:-1])
                | (meas.orientation[1:] != meas.orientation[:-1])]
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
    import allantools  # here, not at the top: it loads scipy.stats (~1 s), which a fit never needs

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


def bases(meas: Measurements, parts: list[slice], taus: np.ndarray, draws: int = 4) -> dict[int, np.ndarray]:
    """Per triad, (T, 3) the Allan variance each unit noise shows after the same deterministic fit as
    the data: the analytic curve times the ratio of the Allan variances after and before the fit,
    summed over `draws` simulations of the noise on these rows (on the same draws, so most of their
    scatter cancels; 4 draws hold the ratio within a few per cent at the top octave). The ratio may
    exceed 1: a fit takes a slow noise's excursions out with the temperature and orientation
    regressors, whose own short-term wiggles then add to the residual."""
    rng = np.random.default_rng(0x41A)
    exact = analytic_basis(taus, meas.row_dt_s)
    systems = []
    for triad in (0, 1):
        design = _design(meas, triad)
        scale = np.sqrt(np.maximum(np.einsum("np,np->p", design, design), 1e-300))
        design = design / scale  # unit columns: the Gram's pseudo-inverse is then well conditioned
        systems.append((design, np.linalg.pinv(design.T @ design, rcond=1e-10, hermitian=True)))
    raw = np.zeros((taus.size, 3))
    kept = np.zeros((2, taus.size, 3))
    for _ in range(draws):
        noise = unit_noises(meas, rng)  # the same draws for both triads: each is fitted on its own
        raw += allan_curve(noise, parts, meas.row_dt_s, taus).adev ** 2
        for triad, (design, inverse) in enumerate(systems):
            kept[triad] += allan_curve(_project(noise, design, inverse), parts, meas.row_dt_s, taus).adev ** 2
    return {triad: exact * kept[triad] / raw for triad in (0, 1)}


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


def excess(sim: AllanCurve, measured: AllanCurve) -> dict[str, float]:
    """Per channel, the largest departure of the simulated Allan deviation beyond the allowance of
    its octave: the target, or the measured curve's 68 % interval on that side where it is wider."""
    assert measured.low is not None and measured.high is not None
    ratio = sim.adev / measured.adev
    above = np.maximum(TARGET, measured.high / measured.adev - 1.0)
    below = np.maximum(TARGET, 1.0 - measured.low / measured.adev)
    over = np.where(ratio >= 1.0, ratio - 1.0 - above, 1.0 - ratio - below)
    return {c: float(max(np.max(over[:, i]), 0.0)) for i, c in enumerate(CHANNELS)}


# Power-law exponent of the frequency spectrum (S_y ~ f^alpha) of each term of the noise model:
# white (angle random walk), flicker (bias instability), random walk (rate random walk).
_ALPHA = (0, -1, -2)


@functools.lru_cache(maxsize=4096)
def _edf(alpha: int, m: int, rows: int) -> float:
    """Greenhall's EDF of the overlapping Allan variance of `rows` frequency values at m rows."""
    import allantools

    return float(allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=rows + 1, overlapping=True))


def confidence(measured: AllanCurve, parts: list[slice], dt: float, params: np.ndarray,
               basis: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(T, 6) twice: the measured curve's 68 % interval. Each record's equivalent degrees of freedom
    (allantools' Greenhall EDF of the overlapping Allan variance) for the term of the fitted model
    that dominates the octave, pooled over the records as the curve is (Satterthwaite, weights the
    numbers of Allan terms). The deterministic fit's share of the slow noise is not in it: at the top
    octave the true scatter is somewhat wider."""
    import allantools

    taus = measured.tau_s
    low = np.empty_like(measured.adev)
    high = np.empty_like(measured.adev)
    for i in range(measured.adev.shape[1]):
        terms = basis[0 if i < 3 else 1][: taus.size] * params[i] ** 2
        alpha = np.array([_ALPHA[k] for k in np.argmax(terms, axis=1)])
        for j, tau in enumerate(taus):
            m = int(round(tau / dt))
            weight = sum_w2 = 0.0
            for part in parts:
                rows = part.stop - part.start
                if tau > (rows - 1) * dt / 2.0:
                    continue
                edf = _edf(int(alpha[j]), m, rows)
                w = rows - 2 * m + 1  # oadev's number of terms at m
                weight += w
                sum_w2 += w * w / edf
            low[j, i], high[j, i] = allantools.confidence_interval(measured.adev[j, i], weight * weight / sum_w2)
    return low, high


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
    measured.low, measured.high = confidence(measured, parts, meas.row_dt_s, params, basis)
    fit = NoiseFit(white={c: float(params[i, 0]) for i, c in enumerate(CHANNELS)},
                   bias_instability={c: float(params[i, 1]) for i, c in enumerate(CHANNELS)},
                   rate_random_walk={c: float(params[i, 2]) for i, c in enumerate(CHANNELS)},
                   measured=measured, before=before, after=after)
    fit.mismatch_before = mismatch(before, measured)
    fit.mismatch_after = mismatch(after, measured)
    fit.excess_before = excess(before, measured)
    fit.excess_after = excess(after, measured)
    log.debug("noise: Allan mismatch after %s, beyond the measured curve's interval %s",
              fit.mismatch_after, fit.excess_after)
    return fit


def octave_table(fit: NoiseFit, channel: str) -> str:
    """One channel's curves per octave as text: measured with its 68 % interval, the simulator's
    noise before and after, and the relative departures (what `mismatch` and `excess` take the
    largest of)."""
    i = CHANNELS.index(channel)
    m = fit.measured
    lines = [f"{channel}: tau_s  measured  [68 % interval]  before  after  after/measured-1"]
    for j, tau in enumerate(m.tau_s):
        interval = "" if m.low is None or m.high is None else f"[{m.low[j, i]:.3g}, {m.high[j, i]:.3g}]"
        lines.append(f"  {tau:8g}  {m.adev[j, i]:.4g}  {interval}  {fit.before.adev[j, i]:.4g}  "
                     f"{fit.after.adev[j, i]:.4g}  {fit.after.adev[j, i] / m.adev[j, i] - 1.0:+.3f}")
    return "\n".join(lines)


def interval_json(curve: AllanCurve) -> dict[str, list[list[float]]] | None:
    """The measured curve's 68 % interval per channel, [low, high] per octave (4 significant digits)."""
    if curve.low is None or curve.high is None:
        return None
    return {c: [[float(f"{lo:.4g}"), float(f"{hi:.4g}")] for lo, hi in zip(curve.low[:, i], curve.high[:, i])]
            for i, c in enumerate(CHANNELS)}
