"""Names and layout shared by the fits: triads, channels, parameter labels."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from labrunner.domain import CHANNELS, ORIENTATIONS

TRIADS: tuple[str, ...] = ("accel", "gyro")
AXES = "xyz"
UNITS = {"accel": "g", "gyro": "deg/s"}
TRIAD_SLICE = {"accel": slice(0, 3), "gyro": slice(3, 6)}
__all__ = ["CHANNELS", "ORIENTATIONS", "TRIADS", "AXES", "UNITS", "TRIAD_SLICE", "param_name", "block_names",
           "describe_missing"]


def param_name(block: int, channel: int) -> str:
    """Label of one error term: block 0 is the bias, block j+1 is S[channel, j]."""
    if block == 0:
        return f"bias {AXES[channel]}"
    j = block - 1
    return f"scale factor {AXES[channel]}" if j == channel else f"misalignment {AXES[channel]}{AXES[j]}"


def block_names() -> list[list[str]]:
    """[channel][block] labels."""
    return [[param_name(b, c) for b in range(4)] for c in range(3)]


def describe_missing(triad: str, missing: Iterable[tuple[int, int]], orientations: Iterable[int],
                     rotating: bool) -> str:
    """A sentence saying which terms cannot be fitted and why."""
    missing = sorted(set(missing))
    names = [param_name(b, c) for c, b in missing]
    present = [ORIENTATIONS[i] for i in sorted(set(int(o) for o in orientations))]
    if triad == "gyro" and not rotating:
        why = "no table rotation in the data"
    else:
        why = "orientations present: " + (", ".join(present) if present else "none")
        if triad == "accel":
            why += " (bias and scale need each axis seen both up and down)"
    return f"{triad}: {', '.join(names)} cannot be fitted ({why})"


def as_channel_dict(values: np.ndarray, triad: str | None = None) -> dict[str, float]:
    """{channel: value} for 6 values, or for 3 values of one triad."""
    chans = CHANNELS if triad is None else CHANNELS[TRIAD_SLICE[triad]]
    return {c: float(v) for c, v in zip(chans, np.asarray(values).ravel())}
