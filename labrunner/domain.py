"""The base layer: names and constants every room of labrunner shares.

Orientations, channels, up vectors, the campaign CSV columns and the reference and room
temperatures live here so that the orchestrator, the analysis, the drivers and the
simulated lab agree on them without importing each other (docs/design.md, "Rooms").
This module imports nothing of the project.
"""

from __future__ import annotations

from typing import Any

import numpy as np

CHANNELS: tuple[str, ...] = ("accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
ACCEL_CHANNELS = CHANNELS[:3]
GYRO_CHANNELS = CHANNELS[3:]

# Which IMU axis points up; the order fixes UP_VECTORS' rows and stored orientation codes.
ORIENTATIONS: tuple[str, ...] = ("x_up", "x_down", "y_up", "y_down", "z_up", "z_down")

T_REF_C = 25.0  # reference temperature of every thermal polynomial: coefficients of (T - T_REF_C)**k
ROOM_C = 23.0  # where a campaign starts and where the IMU is remounted (the chamber is open)
STANDARD_GRAVITY = 9.80665  # m/s^2 per g

# The campaign CSV format (docs/design.md, "Campaign CSV"): one row per sample.
CSV_COLUMNS: tuple[str, ...] = (
    "t_s", "run", "orientation", "chamber_c", "imu_temp_c", "table_rate_dps",
    "ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps",
)
ACCEL_COLUMNS = ("ax_g", "ay_g", "az_g")
GYRO_COLUMNS = ("gx_dps", "gy_dps", "gz_dps")
OUTPUT_COLUMNS = ACCEL_COLUMNS + GYRO_COLUMNS


def up_vector(orientation: str) -> np.ndarray:
    """Body-frame unit vector of local 'up' for an orientation label."""
    try:
        i = ORIENTATIONS.index(orientation)
    except ValueError:
        raise ValueError(f"unknown orientation {orientation!r}; expected one of {', '.join(ORIENTATIONS)}") from None
    v = np.zeros(3)
    v[i // 2] = 1.0 if i % 2 == 0 else -1.0
    return v


UP_VECTORS = np.array([up_vector(o) for o in ORIENTATIONS])  # (6, 3), row per orientation label


def orientation_index(labels: Any) -> np.ndarray:
    """Index into ORIENTATIONS for each label; raises ValueError naming the first unknown one."""
    arr = np.asarray(labels, dtype=object)
    out = np.full(arr.shape, -1, dtype=np.int64)
    for i, name in enumerate(ORIENTATIONS):
        out[arr == name] = i
    if (out < 0).any():
        bad = arr[out < 0][0]
        raise ValueError(f"unknown orientation {bad!r}; expected one of {', '.join(ORIENTATIONS)}")
    return out
