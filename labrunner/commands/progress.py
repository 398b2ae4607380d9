"""The progress bar of `labrunner run` and `resume` (tqdm on stderr): steps, state, the measured
chamber and IMU temperatures, the soak's progress, lab time and the ETA from the measured pace."""

from __future__ import annotations

import logging
import math
import os
import sys
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # annotations only: `labrunner --help` must not load the API (and pandas, the sims)
    from labrunner.api import Progress

log = logging.getLogger(__name__)

REFRESH_S = 0.5  # a soak moves no step for hours: redraw the readings this often anyway
BAR_ROOM = 45  # columns the bar, the percentage, n/total and the elapsed time need at least


def clock_text(seconds: float) -> str:
    """h:mm:ss (d days h:mm:ss past a day), as tqdm writes elapsed time."""
    s = int(round(max(seconds, 0.0)))
    days, s = divmod(s, 86400)
    text = f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"
    return f"{days}d {text}" if days else text


def _c(value: float | None) -> str:
    return "?" if value is None or not math.isfinite(value) else f"{value:.2f}C"


def postfix_parts(p: Progress) -> list[str]:
    """What follows the bar, most wanted first (a narrow terminal drops from the end)."""
    step = p.step
    where = f" {step.orientation} {step.temperature_c:+g}C {step.rate_dps:+g}dps" if step else ""
    parts = [f"{p.state}{where}"]
    if p.eta_s is not None and p.state not in ("fitting", "done"):
        parts.append(f"ETA {clock_text(p.eta_s)}")
    if p.chamber_c is not None or p.imu_temp_c is not None:
        parts.append(f"chamber {_c(p.chamber_c)} IMU {_c(p.imu_temp_c)}")
    soak = p.soak
    if soak is not None:
        what = f"IMU spread {soak.imu_spread_c:.2f}" if soak.sensor == "imu" else f"off {soak.chamber_offset_c:.2f}"
        parts.append(f"soak {what}/{soak.tolerance_c:g}C stable {soak.stable_s:.0f}/{soak.window_s:.0f}s")
    parts.append(f"lab {p.lab_time_s / 3600:.2f} h")
    return parts


def fit_parts(parts: list[str], width: int) -> str:
    """The parts joined, as many as fit in `width` columns (the first always): a line longer than
    the terminal wraps, and tqdm then draws every refresh on a new line."""
    text = parts[0]
    for part in parts[1:]:
        if len(text) + 3 + len(part) > width:
            break
        text += " | " + part
    return text


def _columns() -> int:
    """The width of the terminal the bar is drawn on (stderr's, not stdout's: `run ... > summary.md`
    keeps the bar on the terminal); not a terminal (a log file): no limit worth keeping to."""
    try:
        columns = os.get_terminal_size(sys.stderr.fileno()).columns
    except (AttributeError, OSError, ValueError):  # not a terminal, no descriptor (a test's stream)
        return 250
    return columns if columns > 0 else 250  # a pseudo-terminal without a size says 0


class ProgressBar:
    """A `progress` callback for `labrunner.run`/`resume`; `quiet` makes it do nothing. `initial` is
    the steps recorded before this session: a resumed campaign's bar starts there, not at 0."""

    def __init__(self, total: int, quiet: bool, initial: int = 0) -> None:
        self.bar: Any = None
        self._drawn = time.monotonic()  # when the postfix was last drawn
        self._last: Progress | None = None  # the last state given
        if not quiet:
            from tqdm import tqdm

            try:  # tqdm draws the empty bar at once
                # No {remaining}: tqdm's is steps per second, which a soak throws off by ten times (the
                # ETA in the postfix is the measured pace's, labrunner.runner.pace).
                self.bar = tqdm(total=total, initial=initial, unit="step", file=sys.stderr, dynamic_ncols=True,
                                mininterval=REFRESH_S, bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} steps "
                                                                  "[{elapsed}{postfix}]")
            except OSError as exc:  # stderr already gone: run without a bar (see __call__)
                log.debug("progress bar off: %s", exc)

    def __call__(self, p: Progress) -> None:
        if self.bar is None:
            return
        self._last = p
        try:
            now = time.monotonic()
            due = now - self._drawn >= REFRESH_S  # before that tqdm would not draw: the postfix would not be seen
            if due:
                self.bar.set_postfix_str(fit_parts(postfix_parts(p), max(_columns() - BAR_ROOM, 20)), refresh=False)
                self._drawn = now
            if p.steps_done > self.bar.n:
                self.bar.update(p.steps_done - self.bar.n)  # draws, at most every REFRESH_S
            elif due:
                self.bar.refresh()  # the readings and the soak change while no step does
        except OSError as exc:
            # stderr is gone (`2>&1 | head` exited, a closed terminal): a display must never end a campaign,
            # which the sequencer would do for an error raised in its progress callback.
            log.debug("progress bar off: %s", exc)
            self.bar.disable = True  # tqdm writes nothing more, not even on close
            self.bar = None

    def close(self) -> None:
        if self.bar is not None:
            try:
                if self._last is not None:  # the last state (done, stopped), which a throttled call did not show
                    self.bar.set_postfix_str(fit_parts(postfix_parts(self._last), max(_columns() - BAR_ROOM, 20)),
                                             refresh=False)
                self.bar.close()
            except OSError as exc:  # as in __call__: the run's own summary follows and finds the pipe closed
                log.debug("progress bar off: %s", exc)
            self.bar = None
