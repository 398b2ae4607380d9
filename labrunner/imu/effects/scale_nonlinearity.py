"""Scale non-linearity: the output error grows with the square of the input, k2 * u_i**2."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import ACCEL_CHANNELS, CHANNELS, GYRO_CHANNELS

from ..effect import (
    CampaignFacts,
    Effect,
    Fit,
    FitContext,
    Gap,
    Stream,
    channel_map,
    channel_vector,
    per_channel,
    random_channels,
    scalars,
)

_AXES = ("x", "y", "z")


def _inputs(force_g: np.ndarray, rate_dps: np.ndarray) -> np.ndarray:
    return np.concatenate([np.asarray(force_g, dtype=float), np.asarray(rate_dps, dtype=float)], axis=1)


@dataclass
class ScaleNonlinearity(Effect):
    """Output error grows with the square of the input: error = k2 * u_i**2."""

    name = "scale_nonlinearity"
    order = 60
    what = "output error grows with the square of the input"
    driver = "the input magnitude (several table rates; for accelerometers, axes up and down)"
    json_parameters = "`k2_per_dps`: {channel: error = k2 u^2} (per g for accelerometers)"
    per_channel_columns = True

    k2_per_dps: dict[str, float] = field(default_factory=dict)  # per g for accelerometer channels

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        return cls.from_dict({"k2_per_dps": random_channels(rng, CHANNELS, 3e-3, 4e-5)})

    def validate(self) -> None:
        self.k2_per_dps = channel_map(self.k2_per_dps)

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        u = _inputs(stream.inputs.force_g, stream.inputs.rate_dps)
        return u ** 2 * channel_vector(self.k2_per_dps)[None, :], None

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        u = _inputs(ctx.rows.force_g, ctx.rows.rate_dps)
        sq = u * u
        return {c: sq[:, i: i + 1] for i, c in enumerate(CHANNELS)}

    @classmethod
    def envelope(cls, ctx: FitContext) -> dict[str, np.ndarray]:
        return cls.regressors(ctx, {}, None)

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        return per_channel(self.k2_per_dps)

    @classmethod
    def coverage_gaps(cls, facts: CampaignFacts) -> list[Gap]:
        gaps = []
        for j, axis in enumerate(_AXES):
            if not facts.vertical[j]:
                gaps.append(Gap(f"scale_nonlinearity on accel_{axis}: the {axis} axis was never vertical",
                                (ACCEL_CHANNELS[j],)))
                if facts.rotating:
                    gaps.append(Gap(f"scale_nonlinearity on gyro_{axis}: no rotation about the {axis} axis",
                                    (GYRO_CHANNELS[j],)))
            elif not facts.both_ways[j]:
                gaps.append(Gap(f"scale_nonlinearity on accel_{axis}: the {axis} axis was vertical one way only, so "
                                f"the square of the force cannot be told from the scale factor", (ACCEL_CHANNELS[j],)))
        if not facts.rotating:
            gaps.append(Gap("scale_nonlinearity (gyro): no table rotation in the data", GYRO_CHANNELS))
        return gaps

    @classmethod
    def rate_floor(cls, channel: str, max_rate_dps: float, rate_accuracy: float) -> float:
        # The logged reference rate may be off by the table's accuracy per record: a gyro's
        # squared-rate term smaller than that at the highest rate looks just like it.
        return rate_accuracy * max_rate_dps if channel in GYRO_CHANNELS else 0.0

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        k2 = scalars(fit)
        return {"k2_per_dps": k2}, {"k2_per_dps": k2}
