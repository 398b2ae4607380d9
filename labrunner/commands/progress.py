"""The progress bar of `labrunner run` and `resume` (tqdm on stderr, with the state, step and lab time)."""

from __future__ import annotations

import logging
import sys
from typing import Any

from labrunner.api import Progress

log = logging.getLogger(__name__)


class ProgressBar:
    """A `progress` callback for `labrunner.run`/`resume`; `quiet` makes it do nothing."""

    def __init__(self, total: int, quiet: bool) -> None:
        self.bar: Any = None
        if not quiet:
            from tqdm import tqdm

            try:  # tqdm draws the empty bar at once
                self.bar = tqdm(total=total, unit="step", file=sys.stderr, dynamic_ncols=True, mininterval=0.5,
                                smoothing=0.05, bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} steps "
                                                           "[{elapsed}<{remaining}] {postfix}")
            except OSError as exc:  # stderr already gone: run without a bar (see __call__)
                log.debug("progress bar off: %s", exc)

    def __call__(self, p: Progress) -> None:
        if self.bar is None:
            return
        try:
            if p.steps_done > self.bar.n:
                self.bar.update(p.steps_done - self.bar.n)
            step = p.step
            where = f"{step.orientation} {step.temperature_c:+g}C {step.rate_dps:+g}dps" if step else ""
            self.bar.set_postfix_str(f"{p.state:13s} {where} lab time {p.lab_time_s / 3600:6.2f} h", refresh=False)
        except OSError as exc:
            # stderr is gone (`2>&1 | head` exited, a closed terminal): a display must never end a campaign,
            # which the sequencer would do for an error raised in its progress callback.
            log.debug("progress bar off: %s", exc)
            self.bar.disable = True  # tqdm writes nothing more, not even on close
            self.bar = None

    def close(self) -> None:
        if self.bar is not None:
            try:
                self.bar.close()
            except OSError as exc:  # as in __call__: the run's own summary follows and finds the pipe closed
                log.debug("progress bar off: %s", exc)
            self.bar = None
