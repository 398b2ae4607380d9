"""Is the IMU mounted as planned? Gravity says: at rest the accelerometer reads +1 g along the up axis.

After a remount (and at preflight) the sequencer reads a second or so of frames through the IMU
driver, averages the specific force and compares its direction with the planned orientation's up
vector (`labrunner.domain.UP_VECTORS`). The mount counts as right when the angle is within
`mount_check.max_angle_deg` and the magnitude within `gravity_tolerance_g` of 1 g; a remount the
operator skipped, or made about the wrong axis, is then caught before anything is recorded under
the wrong label. The verdict names what was measured ("x axis up, 3.0° off"), for the event and
for the operator's next prompt. On resume, the same verdict and the chamber's distance from the
next step's setpoint decide whether the campaign can go on in place (`in_place`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from labrunner.domain import ORIENTATIONS, UP_VECTORS, up_vector
from labrunner.drivers.protocols import Imu

log = logging.getLogger(__name__)


def axis_words(orientation: str) -> str:
    """'x_up' -> 'x axis up'."""
    axis, _, way = orientation.partition("_")
    return f"{axis} axis {way}"


@dataclass(frozen=True)
class MountVerdict:
    """What a second of accelerometer frames says about the mount, against the planned orientation."""

    planned: str
    frames: int
    mean_g: tuple[float, float, float] | None  # mean specific force (None: no frames)
    magnitude_g: float | None
    measured: str | None  # the orientation whose up axis is nearest the measured force
    off_measured_deg: float | None  # angle between the force and that orientation's up axis
    off_planned_deg: float | None  # angle between the force and the planned up axis
    ok: bool

    def measured_words(self) -> str:
        """'x axis up, 3.0° off, 1.002 g' (or what is missing)."""
        if not self.frames:
            return "no IMU frames"
        if self.measured is None or self.magnitude_g is None or self.off_measured_deg is None:
            return f"{self.magnitude_g or 0.0:.3f} g, no direction"
        return f"{axis_words(self.measured)}, {self.off_measured_deg:.1f}° off, {self.magnitude_g:.3f} g"

    def describe(self) -> str:
        """'measured: x axis up, 3.0° off, 1.002 g; planned: y_down'."""
        return f"measured: {self.measured_words()}; planned: {self.planned}"

    def detail(self) -> dict[str, Any]:
        """The verdict as event detail (JSON)."""
        return {"planned": self.planned, "measured": self.measured, "frames": self.frames,
                "mean_g": list(self.mean_g) if self.mean_g is not None else None, "magnitude_g": self.magnitude_g,
                "off_planned_deg": self.off_planned_deg, "off_measured_deg": self.off_measured_deg, "ok": self.ok}


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def judge(accel_g: np.ndarray, planned: str, *, max_angle_deg: float, gravity_tolerance_g: float) -> MountVerdict:
    """The verdict on (N, 3) accelerometer frames in g for the `planned` orientation."""
    up = up_vector(planned)  # raises ValueError for an unknown label
    accel = np.asarray(accel_g, dtype=float).reshape(-1, 3)
    accel = accel[np.isfinite(accel).all(axis=1)]
    if not len(accel):
        return MountVerdict(planned, 0, None, None, None, None, None, ok=False)
    mean = accel.mean(axis=0)
    magnitude = float(np.linalg.norm(mean))
    if magnitude < 1e-6:  # no force at all: no direction to name
        return MountVerdict(planned, len(accel), (0.0, 0.0, 0.0), magnitude, None, None, None, ok=False)
    nearest = int(np.argmax(UP_VECTORS @ mean))
    off_planned = _angle_deg(mean, up)
    ok = off_planned <= max_angle_deg and abs(magnitude - 1.0) <= gravity_tolerance_g
    return MountVerdict(planned, len(accel), (float(mean[0]), float(mean[1]), float(mean[2])), magnitude,
                        ORIENTATIONS[nearest], _angle_deg(mean, UP_VECTORS[nearest]), off_planned, ok=ok)


def read_accel(imu: Imu, wait: Callable[[float], None], seconds: float, timeout_s: float) -> np.ndarray:
    """`seconds` of accelerometer frames through the IMU driver, (N, 3) in g; `wait` lets clock time pass."""
    n = max(1, int(round(seconds * imu.rate_hz)))
    start = imu.begin_record()
    wait(seconds)
    rec = imu.end_record(start, n, timeout_s=timeout_s)
    log.debug("mount check: %d of %d frames", len(rec), n)
    return np.asarray(rec.accel_g, dtype=float).reshape(-1, 3)


@dataclass(frozen=True)
class InPlace:
    """Whether a resumed campaign may go on without a remount, and why (or why not)."""

    ok: bool
    reason: str


def in_place(verdict: MountVerdict | None, chamber_c: float, setpoint_c: float, tolerance_c: float) -> InPlace:
    """The lab as a crash left it: the IMU still stands as the next step plans (gravity), and the chamber is
    within `tolerance_c` of that step's setpoint. `verdict` None: the mount cannot be checked (check off)."""
    if verdict is None:
        return InPlace(False, "the mount check is off (mount_check.enabled: false), so the mount cannot be "
                              "confirmed")
    if not verdict.ok:
        return InPlace(False, f"the IMU does not stand as planned ({verdict.describe()})")
    away = abs(chamber_c - setpoint_c)
    if not math.isfinite(away) or away > tolerance_c:
        return InPlace(False, f"chamber {chamber_c:.2f} C is {away:.2f} C from the step's {setpoint_c:g} C "
                              f"(resume.chamber_tolerance_c {tolerance_c:g} C)")
    return InPlace(True, f"IMU {verdict.measured_words()}, as planned ({verdict.planned}); chamber "
                         f"{chamber_c:.2f} C within {tolerance_c:g} C of {setpoint_c:g} C")


__all__ = ["InPlace", "MountVerdict", "axis_words", "in_place", "judge", "read_accel"]
