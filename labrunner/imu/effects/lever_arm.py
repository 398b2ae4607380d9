"""Lever arm: the accelerometer sits r_m (body frame, metres) off the rotation axis and senses
the centripetal acceleration w x (w x r) / g0.

One exact form for the simulator and the diagnosis: accelerometer channel i senses
sum_j (w_i w_j - delta_ij |w|^2) r_j / g0, so its regressors are those three columns and its
coefficients the whole r. On a rate table the rotation is about one body axis: only r_i
enters channel i (the other columns are zero) and the rotation axis senses nothing. (The
tangential term, present only while the table accelerates, is neglected.)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import ACCEL_CHANNELS, CHANNELS, STANDARD_GRAVITY

from ..effect import CampaignFacts, Effect, Fit, FitContext, Gap, Stream


def centripetal_columns(rate_dps: np.ndarray) -> np.ndarray:
    """(N, 3, 3): [n, i, j] = (w_i w_j - delta_ij |w|^2) / g0, so accel error i = cols[:, i] @ r."""
    w = np.deg2rad(np.asarray(rate_dps, dtype=float).reshape(-1, 3))
    outer = w[:, :, None] * w[:, None, :]
    return (outer - np.sum(w * w, axis=1)[:, None, None] * np.eye(3)[None]) / STANDARD_GRAVITY


@dataclass
class LeverArm(Effect):
    """The accelerometer sits r_m (body frame, metres) off the rotation axis: it senses the
    centripetal acceleration w x (w x r) / g0, which grows with the square of the table rate on
    the horizontal axes."""

    name = "lever_arm"
    order = 80
    what = "the accelerometer sits off the table axis and senses centripetal acceleration"
    driver = "the table rate (rate squared on the horizontal axes)"
    json_parameters = "`r_m`: [x, y, z] metres, body frame"
    acts_on = ACCEL_CHANNELS
    per_channel_columns = True
    separates = {
        "scale_nonlinearity":
            "spin the table with the IMU in more orientations: a lever arm acts on the horizontal "
            "accelerometer axes only, a squared-input error on the axis that carries the input",
    }

    r_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        return cls.from_dict({"r_m": rng.uniform(-0.08, 0.08, 3).tolist()})

    def validate(self) -> None:
        r = np.asarray(self.r_m, dtype=float)
        if r.shape != (3,):
            raise ValueError("effect lever_arm: r_m must be 3 numbers (metres, body frame)")
        self.r_m = r.tolist()

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        w = np.deg2rad(np.asarray(stream.inputs.rate_dps, dtype=float).reshape(-1, 3))
        r = np.asarray(self.r_m, dtype=float)
        err = np.zeros((w.shape[0], len(CHANNELS)))
        err[:, :3] = np.cross(w, np.cross(w, r[None, :])) / STANDARD_GRAVITY
        return err, None

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        cols = centripetal_columns(ctx.rows.rate_dps)
        return {c: np.ascontiguousarray(cols[:, i, :]) for i, c in enumerate(ACCEL_CHANNELS)}

    @classmethod
    def envelope(cls, ctx: FitContext) -> dict[str, np.ndarray]:
        return cls.regressors(ctx, {}, None)

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        r = np.asarray(self.r_m, dtype=float)
        return {c: r.copy() for c in ACCEL_CHANNELS}

    @classmethod
    def coverage_gaps(cls, facts: CampaignFacts) -> list[Gap]:
        if not facts.rotating:
            return [Gap("lever_arm: no table rotation in the data", ACCEL_CHANNELS)]
        return []

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        # Each channel fits the whole r, but sees only the components its columns carry: take
        # every component from the channel that determines it best (none: 0).
        r = []
        for j in range(3):
            info = {c: float(fit.schur[c][j, j]) if c in fit.schur else 0.0 for c in fit.coef}
            best = max(info, key=lambda c: info[c], default=None)
            r.append(float(fit.coef[best][j]) if best is not None and info[best] > 0 else 0.0)
        return {"r_m": r}, {"r_m": r}
