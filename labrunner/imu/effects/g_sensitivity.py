"""g-sensitivity: gyro output depends on specific force, gyro += M f (M in deg/s per g)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import CHANNELS, GYRO_CHANNELS

from ..effect import CampaignFacts, Effect, Fit, FitContext, Gap, Stream, same_for


@dataclass
class GSensitivity(Effect):
    """Gyro output depends on specific force: gyro += M f, M in deg/s per g."""

    name = "g_sensitivity"
    order = 50
    what = "gyro output depends on specific force"
    driver = "orientation (specific force) independently of power-ons"
    json_parameters = "`matrix_dps_per_g`: 3x3, rows gyro x y z, columns force x y z"
    acts_on = GYRO_CHANNELS

    matrix_dps_per_g: list[list[float]] = field(default_factory=lambda: [[0.0] * 3 for _ in range(3)])

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        return cls.from_dict({"matrix_dps_per_g": (rng.uniform(-0.08, 0.08, (3, 3))).tolist()})

    def validate(self) -> None:
        m = np.asarray(self.matrix_dps_per_g, dtype=float)
        if m.shape != (3, 3):
            raise ValueError("effect g_sensitivity: matrix_dps_per_g must be 3x3")
        self.matrix_dps_per_g = m.tolist()

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        force = np.asarray(stream.inputs.force_g, dtype=float).reshape(-1, 3)
        err = np.zeros((force.shape[0], len(CHANNELS)))
        err[:, 3:] = force @ np.asarray(self.matrix_dps_per_g, dtype=float).T
        return err, None

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        return same_for(GYRO_CHANNELS, np.asarray(ctx.rows.force_g, dtype=float))

    @classmethod
    def envelope(cls, ctx: FitContext) -> dict[str, np.ndarray]:
        return cls.regressors(ctx, {}, None)

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        m = np.asarray(self.matrix_dps_per_g, dtype=float)
        return {c: m[i].copy() for i, c in enumerate(GYRO_CHANNELS)}

    @classmethod
    def coverage_gaps(cls, facts: CampaignFacts) -> list[Gap]:
        gaps = []
        n = len(facts.orientations)
        if not facts.bias_separable and n > 1:
            gaps.append(Gap("g_sensitivity: determined only up to a constant per gyro axis (absorbed by the gyro "
                            "bias): no axis was both up and down"))
        if not any(facts.vertical) or n < 2:
            gaps.append(Gap("g_sensitivity: a single orientation, the specific force never changes", GYRO_CHANNELS))
        return gaps

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        m = np.zeros((3, 3))
        for c, b in fit.coef.items():
            m[GYRO_CHANNELS.index(c)] = b
        return {"matrix_dps_per_g": m.tolist()}, {"matrix_dps_per_g": m.tolist()}
