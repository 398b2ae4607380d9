"""The ETA of a running campaign from its measured pace.

Steps are no measure of the work left: a soak takes a hundred record steps' lab time, so an ETA
from steps per second (tqdm's) swings by a factor of ten between a soak and the records after it.
Progress is counted here in *planned lab seconds* instead (`Procedure.estimated_step_ends_s`), and
the wall time left is

    lab time left  = planned lab time left x (lab time spent / planned lab time done)
    wall time left = lab time left / lab seconds per wall second

The first factor corrects the plan by how it compared so far (the quick procedure's soaks end ~12 %
sooner than planned); it starts at the plan's own figure and moves to the measured ratio as work is
done, so it never jumps. The second is the clock's own rate when it has one (1 on a real lab, N on a
lab clock running N times faster, to rehearse against `labrunner sim serve --speed N`): there the
ETA is the lab time left. A dry run's virtual clock has no rate; it is measured, as the mean over
the session: a soak passes hours of lab time in a tenth of a second and a record seconds of lab time
in a hundredth, so any window shorter than a temperature cycle would swing by that much.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

PRIOR_FRACTION = 0.05  # the plan counts as this much measured work: its correction grows in, never jumps
MIN_FRACTION = 0.02  # a measured rate needs this much of the plan done in the session ...
MIN_WALL_S = 0.2  # ... and this long a stretch of wall time


@dataclass(frozen=True)
class Schedule:
    """A plan's lab time, step by step: `ends[k]` is the planned lab time at which step k ends."""

    ends: tuple[float, ...]

    @classmethod
    def of(cls, ends: Sequence[float]) -> Schedule:
        if not ends:
            raise ValueError("a schedule needs at least one step")
        return cls(tuple(float(e) for e in ends))

    @property
    def total_s(self) -> float:
        return self.ends[-1]

    def start_of(self, k: int) -> float:
        return self.ends[k - 1] if k > 0 else 0.0

    def done_s(self, k: int | None, lab_in_step_s: float) -> float:
        """Planned lab seconds done while working on step k (None: all recorded) for `lab_in_step_s`
        of lab time: the steps before it and as much of its own share as has passed, never more (a
        soak that outlasts the plan holds progress where it is, so the ETA grows as it should)."""
        if k is None:
            return self.total_s
        start = self.start_of(k)
        return start + min(max(lab_in_step_s, 0.0), self.ends[k] - start)


@dataclass(frozen=True)
class Eta:
    """What the estimator says at one moment."""

    lab_left_s: float  # lab time to the last step's end
    wall_left_s: float | None  # wall time to it; None while the pace is not known yet
    lab_per_wall: float | None  # lab seconds per wall second: the clock's, or measured
    plan_ratio: float  # lab time spent per planned lab second so far (1.0: as planned)


class PaceEstimator:
    """Feed it (wall, lab, planned done) at each moment of a session; it returns the `Eta`.

    `lab_per_wall` is the clock's known rate (None for a virtual clock: measured). The first
    update is the session's origin: a resumed campaign measures its own pace, from where it resumed.
    """

    def __init__(self, planned_total_s: float, *, lab_per_wall: float | None = None) -> None:
        if planned_total_s <= 0:
            raise ValueError(f"planned lab time must be > 0, got {planned_total_s}")
        self.planned_total_s = planned_total_s
        self.clock_rate = lab_per_wall
        self._origin: tuple[float, float, float] | None = None

    def update(self, wall_s: float, lab_s: float, planned_done_s: float) -> Eta:
        if self._origin is None:
            self._origin = (wall_s, lab_s, planned_done_s)
        wall0, lab0, planned0 = self._origin
        lab_spent = max(lab_s - lab0, 0.0)
        planned_spent = max(planned_done_s - planned0, 0.0)
        prior = PRIOR_FRACTION * self.planned_total_s
        ratio = (lab_spent + prior) / (planned_spent + prior)
        lab_left = max(self.planned_total_s - planned_done_s, 0.0) * ratio
        rate = self.clock_rate
        wall = wall_s - wall0
        if rate is None and wall >= MIN_WALL_S and planned_spent >= MIN_FRACTION * self.planned_total_s \
                and lab_spent > 0:
            rate = lab_spent / wall
        return Eta(lab_left_s=lab_left, wall_left_s=None if rate is None else lab_left / rate, lab_per_wall=rate,
                   plan_ratio=ratio)
