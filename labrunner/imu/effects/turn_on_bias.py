"""Turn-on bias: a different constant offset after each power-on, normal with spread sigma.

`offsets` pins the offsets of listed runs ({run number: {channel: offset}}), so a model
fitted to a measured campaign reproduces that campaign's runs; other runs draw from
sigma, one draw per (model seed, run), so every chunk of a stream agrees.

In the diagnosis the regressors are indicators of every run but the first: the baseline's
bias constant holds the first run's offset (`intercept`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import CHANNELS

from ..effect import (
    CampaignFacts,
    Effect,
    Fit,
    FitContext,
    Gap,
    Stream,
    channel_map,
    channel_vector,
    random_channels,
    same_for,
)

# Directions of the per-run offsets the data determines within 10x the best standard error:
# nearly aliased ones (runs that coincide with temperatures, up to a little self-heating)
# would only add estimation noise.
_IDENTIFIED = 1e-2


def run_offsets(runs: np.ndarray, seed: int, sigma: dict[str, float],
                pinned: dict[str, dict[str, float]]) -> np.ndarray:
    """(N, 6) offsets of the runs: pinned ones as given, others one normal draw per (seed, run)."""
    runs = np.asarray(runs, dtype=np.int64)
    out = np.zeros((runs.size, len(CHANNELS)))
    if runs.size == 0:
        return out
    spread = channel_vector(sigma)
    fixed = {int(k): channel_vector(v) for k, v in pinned.items()}
    for r in np.unique(runs):
        if int(r) in fixed:
            out[runs == r] = fixed[int(r)]
            continue
        z = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(r) & 0xFFFFFFFF, 0x7B1A5]).standard_normal(6)
        out[runs == r] = z * spread
    return out


def turn_on_sigma(offsets: np.ndarray, schur: np.ndarray, cov: np.ndarray) -> float:
    """Spread of per-run offsets from their estimates relative to the first run.

    Offsets d_r ~ N(0, s^2) estimated relative to run 1: b = d[1:] - d[0], cov s^2 (I + 11').
    Directions the rest of the model can also explain (runs that coincide with
    orientations or temperatures) are not estimable: only the part of b in the range of
    the term's Schur complement counts, with its expected size and estimation noise.
    """
    if offsets.size == 0:
        return 0.0
    w, v = np.linalg.eigh(schur)
    keep = w > _IDENTIFIED * max(float(w.max()), 1e-300)
    if not keep.any():
        return 0.0
    proj = v[:, keep] @ v[:, keep].T
    ones = np.ones(offsets.size)
    dof = float(np.trace(proj) + ones @ proj @ ones)
    noise = float(np.trace(proj @ cov))
    return float(np.sqrt(max(float(offsets @ proj @ offsets) - noise, 0.0) / dof))


def offsets_roughness(coef: np.ndarray, schur: np.ndarray) -> float:
    """Von Neumann ratio of the fitted per-run offsets in run order: mean squared step from one
    run to the next over their variance. Independent offsets (turn-on bias) give about 2; a
    slow drift sampled run by run gives steps much smaller than its spread (near 0). Only the
    identifiable part of the offsets counts (see turn_on_sigma)."""
    w, v = np.linalg.eigh(schur)
    keep = w > _IDENTIFIED * max(float(w.max()), 1e-300)
    b = (v[:, keep] @ v[:, keep].T) @ coef if keep.any() else coef * 0.0
    d = np.concatenate([[0.0], b])
    d = d - d.mean()
    denom = float(np.sum(d * d))
    return float(np.sum(np.diff(d) ** 2) / denom) if denom > 0 else 0.0


@dataclass
class TurnOnBias(Effect):
    """A different constant offset after each power-on, normal with spread sigma."""

    name = "turn_on_bias"
    order = 40
    what = "a different constant offset after each power-on"
    driver = "power-ons (runs) that do not coincide with orientation or temperature changes"
    json_parameters = "`sigma`: {channel: spread of the per-run offsets}, `runs`"
    separates = {
        "g_sensitivity":
            "every orientation change coincides with a power-on, so per-orientation offsets (g-sensitivity) and "
            "per-run offsets (turn-on bias) fit alike: power-cycle the IMU within an orientation (e.g. at every "
            "temperature), or come back to an orientation after a later power-on",
        "scale_nonlinearity":
            "the squared input changes only when the IMU is remounted (a power-on), so a squared-force term and "
            "per-run offsets fit alike: power-cycle within an orientation, or for the gyro spin the table at "
            "several rates within one power-on",
        "hysteresis":
            "each power-on covers one temperature direction, so the heating/cooling branch offset and per-run "
            "offsets fit alike: reverse the temperature direction within one power-on (up and down in the same "
            "run), or power-cycle at every temperature",
        "warmup":
            "a slow power-on transient and a per-run offset look alike over short runs: record longer after "
            "each power-on, or power-cycle more often",
    }

    sigma: dict[str, float] = field(default_factory=dict)
    offsets: dict[str, dict[str, float]] = field(default_factory=dict)

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        # Drawn offsets for most runs, a few pinned (as a fitted model has them).
        pinned = {str(int(r)): random_channels(rng, CHANNELS, 4e-3, 0.1) for r in rng.choice(8, size=2, replace=False)}
        return cls.from_dict({"sigma": random_channels(rng, CHANNELS, 4e-3, 0.1, signed=False), "offsets": pinned})

    def validate(self) -> None:
        self.sigma = channel_map(self.sigma)
        try:
            self.offsets = {str(int(k)): channel_map(v) for k, v in (self.offsets or {}).items()}
        except (TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"effect turn_on_bias: offsets must map run numbers to channel offsets ({exc})") from None

    def run_offsets(self, runs: np.ndarray, seed: int) -> np.ndarray:
        """(N, 6) offset of each sample's run."""
        return run_offsets(runs, seed, self.sigma, self.offsets)

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        return self.run_offsets(stream.inputs.run, stream.seed), None

    # -- the diagnosis -------------------------------------------------------------------------

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        cols = (np.asarray(ctx.rows.run)[:, None] == ctx.run_ids[None, 1:]).astype(float)
        return same_for(CHANNELS, cols)

    @classmethod
    def block_regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                         ) -> dict[str, np.ndarray] | None:
        # Blocks never straddle a power-on, so block means are the indicators themselves.
        cols = (ctx.blocks.run[:, None] == ctx.run_ids[None, 1:]).astype(float)
        return same_for(CHANNELS, cols)

    @classmethod
    def predict(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None, channel: str,
                coef: np.ndarray) -> np.ndarray:
        offsets = np.concatenate([[0.0], coef])
        return offsets[np.searchsorted(ctx.run_ids, ctx.rows.run)]

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        per_run = self.run_offsets(ctx.run_ids, seed)
        return {c: per_run[1:, i] - per_run[0, i] for i, c in enumerate(CHANNELS)}

    def intercept(self, ctx: FitContext, seed: int) -> np.ndarray:
        return self.run_offsets(ctx.run_ids[:1], seed)[0]

    @classmethod
    def consistent(cls, coef: np.ndarray, schur: np.ndarray) -> bool:
        # Below half the roughness of independent offsets the offsets follow a drift, not power-ons.
        # Too few runs to tell: accept.
        return coef.size < 5 or offsets_roughness(coef, schur) >= 1.0

    @classmethod
    def coverage_gaps(cls, facts: CampaignFacts) -> list[Gap]:
        if facts.runs < 2:
            return [Gap("turn_on_bias: one power-on (run) in the data", CHANNELS)]
        return []

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        sigma: dict[str, float] = {}
        offsets: dict[str, dict[str, float]] = {str(int(r)): {} for r in ctx.run_ids}
        for c, b in fit.coef.items():
            sigma[c] = turn_on_sigma(b, fit.schur[c], fit.cov[c])
            offsets[str(int(ctx.run_ids[0]))][c] = 0.0
            for r, value in zip(ctx.run_ids[1:], b):
                offsets[str(int(r))][c] = float(value)
        return {"sigma": sigma, "runs": int(ctx.run_ids.size)}, {"sigma": sigma, "offsets": offsets}
