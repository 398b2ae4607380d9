"""Campaign makers shared by the calibration tests (imported by conftest and the tests)."""

from __future__ import annotations

import pandas as pd

from labrunner.imu.model import ImuModel, default_imu_model
from labrunner.sims.campaign import CampaignPlan, synthesize
from labrunner.sims.world import SimLabConfig

# A smooth step in temperature that a cubic cannot follow (amplitudes: g and deg/s).
NONLINEAR_AMPLITUDE = {"accel_x": 0.01, "accel_y": -0.008, "accel_z": 0.012,
                       "gyro_x": 0.3, "gyro_y": -0.25, "gyro_z": 0.35}


def make_campaign(model: ImuModel | None = None, seed: int = 0, **plan: object) -> pd.DataFrame:
    return synthesize(CampaignPlan(**plan), SimLabConfig(imu_model=model or default_imu_model(), seed=seed))


def nonlinear_model() -> ImuModel:
    return default_imu_model().with_effects(
        temperature_nonlinearity={"amplitude": NONLINEAR_AMPLITUDE, "center_c": 10.0, "width_c": 4.0})
