"""Bounded retry with exponential backoff, shared by the drivers."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TypeVar

from .errors import InstrumentError, InstrumentRefused, LimitError

log = logging.getLogger(__name__)
T = TypeVar("T")
Sleep = Callable[[float], None]


def with_retry(action: Callable[[], T], *, retries: int, backoff_s: float, sleep: Sleep = time.sleep,
               on_retry: Callable[[int, InstrumentError], None] | None = None) -> T:
    """Run `action`; on a transient InstrumentError retry up to `retries` times, doubling the wait.

    Refusals and limit errors are answers, not transients, and are raised at once.
    `sleep` is the caller's clock (a dry run's backoff costs no real time).
    """
    attempt = 0
    while True:
        try:
            return action()
        except (LimitError, InstrumentRefused):
            raise
        except InstrumentError as exc:
            if attempt >= retries:
                if retries:
                    log.warning("giving up after %d attempt(s): %s", attempt + 1, exc)
                raise
            wait = backoff_s * (2 ** attempt)
            # A retry is the driver doing its job; the campaign's events record it too.
            log.info("retry %d of %d in %.3g s after: %s", attempt + 1, retries, wait, exc)
            if on_retry:
                on_retry(attempt + 1, exc)
            sleep(wait)
            attempt += 1
