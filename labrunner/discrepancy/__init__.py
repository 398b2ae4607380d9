"""What the simulation gets wrong: diagnose measured campaigns against the simulator's IMU model.

`diagnose(frame)` fits the simulator's baseline (`labrunner.imu`) (Eq. 1 with cubic thermal terms) to
measured rows, tests every candidate cause on held-out time blocks against a drift model,
names the causes the data supports (and the ones it cannot tell apart), builds the
extended `ImuModel`, and measures the held-out gain. `labrunner diagnose` is the CLI.
"""

from __future__ import annotations

import importlib
from typing import Any

# Exported lazily (PEP 562): the calibration imports `discrepancy.measurements` and
# `discrepancy.temperature` for their estimators, which should not load the whole diagnosis.
_EXPORTS = {
    "CAUSE_ORDER": "terms",
    "DiagnoseOptions": "diagnose",
    "Diagnosis": "diagnose",
    "Finding": "diagnose",
    "Gain": "diagnose",
    "Measurements": "measurements",
    "check_model": "extend",
    "diagnose": "diagnose",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    globals()[name] = value
    return value
