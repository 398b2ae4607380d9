"""What the simulation gets wrong: diagnose measured campaigns against the simulator's IMU model.

`diagnose(frame)` fits the simulator's baseline (`labrunner.imu`) (Eq. 1 with cubic thermal terms) to
measured rows, tests every candidate cause on held-out time blocks against a drift model,
names the causes the data supports (and the ones it cannot tell apart), builds the
extended `ImuModel`, and measures the held-out gain. `labrunner diagnose` is the CLI.
"""

from .diagnose import DiagnoseOptions, Diagnosis, Finding, Gain, diagnose
from .extend import check_model
from .measurements import Measurements
from .terms import CAUSE_ORDER

__all__ = [
           "CAUSE_ORDER",
           "DiagnoseOptions",
           "Diagnosis",
           "Finding",
           "Gain",
           "Measurements",
           "check_model",
           "diagnose",
]
