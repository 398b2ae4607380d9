"""Synthesized campaigns shared by the calibration tests (session-scoped: each is made once)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from labrunner.sims.campaign import triangular_rates

from calib_campaigns import make_campaign, nonlinear_model


@pytest.fixture(scope="session")
def cubic_campaign() -> pd.DataFrame:
    """Default (cubic) IMU, 7 temperatures, 8 rates, 1 s averaged rows: 20k rows."""
    return make_campaign(seed=11, temperatures_c=(-25.0, -5.0, 5.0, 15.0, 35.0, 45.0, 55.0), average_s=1.0)


@pytest.fixture(scope="session")
def nonlinear_campaign() -> pd.DataFrame:
    """Non-cubic temperature dependence, 9 temperatures, 16 rates, 1 s averaged rows."""
    return make_campaign(nonlinear_model(), seed=12, temperatures_c=tuple(np.arange(-25.0, 56.0, 10.0)),
                         rates_dps=triangular_rates(100.0, 25.0), average_s=1.0)
