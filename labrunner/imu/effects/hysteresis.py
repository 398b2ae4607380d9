"""Hysteresis: heating and cooling branches differ at the same temperature.

The offset is width/2 * h, h in [-1, 1] the branch state: each temperature step dT pulls
it towards sign(dT) by a fraction 1 - exp(-|dT| / travel_c), so a soak keeps the branch
the last excursion left.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from labrunner.domain import CHANNELS

from ..effect import (
    RAMP_C_PER_MIN,
    CampaignFacts,
    Effect,
    Fit,
    FitContext,
    Gap,
    Nonlinear,
    Stream,
    channel_map,
    channel_vector,
    per_channel,
    random_channels,
    same_for,
    scalars,
)
from ..recursions import branch_state, play_state

DEFAULT_TRAVEL_C = 2.0  # also the travel assumed when only soaks are logged (any well below the steps will do)
MIN_BRANCH_OVERLAP_C = 5.0  # temperature span reached both heating and cooling, to see two branches


@dataclass
class Hysteresis(Effect):
    """Heating and cooling branches differ: offset = width/2 * h, h in [-1, 1] the branch state."""

    name = "hysteresis"
    order = 20
    what = "heating and cooling branches differ at the same temperature"
    driver = "the direction of temperature change (reach temperatures from both sides)"
    json_parameters = ("`width`: {channel: heating minus cooling}, `travel_c` (degC of travel that moves the branch "
                       "by 1 - 1/e)")
    separates = {
        "g_sensitivity":
            "each orientation is measured in one temperature direction: measure every orientation both heating "
            "and cooling",
    }

    width: dict[str, float] = field(default_factory=dict)  # heating minus cooling, sensor units
    travel_c: float = DEFAULT_TRAVEL_C  # temperature travel that moves the branch state by 1 - 1/e

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        return cls.from_dict({"width": random_channels(rng, CHANNELS, 3e-3, 0.15),
                              "travel_c": float(rng.uniform(0.5, 6.0))})

    def validate(self) -> None:
        self.width = channel_map(self.width)
        self.travel_c = float(self.travel_c)
        if self.travel_c <= 0:
            raise ValueError("effect hysteresis: travel_c must be > 0")

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        h0 = 0.0 if stream.carried is None else float(stream.carried)
        h = play_state(np.asarray(stream.inputs.temp_c, dtype=float), self.travel_c, h0=h0, temp0=stream.temp0)
        return 0.5 * h[:, None] * channel_vector(self.width)[None, :], float(h[-1])

    @classmethod
    def nonlinear(cls, ctx: FitContext) -> tuple[Nonlinear, ...]:
        # Soaked data alone shows the branch offset, not how fast the branch changes: the travel
        # needs temperature reversals during logged ramps.
        grid = (tuple(np.round(np.geomspace(ctx.min_travel_c, 12.0, 10), 3)) if ctx.ramps_logged
                else (DEFAULT_TRAVEL_C,))
        return (Nonlinear("travel_c", grid),)

    @classmethod
    def nonlinear_names(cls) -> tuple[str, ...]:
        return ("travel_c",)

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        h = branch_state(ctx.rows.temp_c, theta["travel_c"], ctx.remounts, ctx.path_via_c)
        return same_for(CHANNELS, 0.5 * h)  # coefficient = heating minus cooling

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        return per_channel(self.width)

    @classmethod
    def envelope(cls, ctx: FitContext) -> dict[str, np.ndarray]:
        return same_for(CHANNELS, np.column_stack([branch_state(ctx.rows.temp_c, travel, ctx.remounts, ctx.path_via_c)
                                                   for travel in (0.5, 2.0, 8.0)]))

    @classmethod
    def coverage_gaps(cls, facts: CampaignFacts) -> list[Gap]:
        gaps = []
        if facts.power_ons_within_an_orientation > 0 and facts.max_temperature_rate_c_per_min < RAMP_C_PER_MIN:
            gaps.append(Gap("hysteresis: the IMU is power-cycled between soaks and the ramps are not logged, so the "
                            "self-heating after each power-on moves the branch where the log cannot see it", CHANNELS))
        if facts.branch_overlap_c < MIN_BRANCH_OVERLAP_C:
            heating, cooling = facts.branch_rows  # the claim, with the rows it is about
            gaps.append(Gap(f"hysteresis: no temperature range was reached both while heating and while cooling "
                            f"(over {MIN_BRANCH_OVERLAP_C:g} degC): {heating} rows heating, {cooling} cooling rows "
                            f"inside the range reached heating, {facts.branch_overlap_c:.1f} degC in common",
                            CHANNELS))
        return gaps

    @classmethod
    def resolution_limit(cls, ctx: FitContext) -> str | None:
        return f"hysteresis with a travel below {ctx.min_travel_c:.2g} degC"

    @classmethod
    def notes(cls, ctx: FitContext) -> list[str]:
        if ctx.ramps_logged:
            return []
        return [f"hysteresis travel_c: no ramps logged, so it is fixed at {DEFAULT_TRAVEL_C:g} degC; the width is "
                "the branch offset between soaks reached by heating and by cooling"]

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        width = scalars(fit)
        return ({"width": width, "travel_c": fit.theta["travel_c"]},
                {"width": width, "travel_c": fit.theta["travel_c"]})
