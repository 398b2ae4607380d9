"""The thread count of numerical work, set deliberately (threadpoolctl), not left to OpenBLAS's default.

OpenBLAS starts one thread per core and wakes them for every product. The fits and the diagnosis multiply
many thin matrices (per-record designs, per-fold Grams of a few dozen columns), where the pool costs more
than it gives, and on a busy two-core machine the threads fight the other process: measured here,
`fit --no-eval` took 43.9 s with the default against 17.0 s on one thread (load 2.4-3.5), and a 5600 x 17
Gram 1.1 ms against 0.11 ms. So analysis runs on `LABRUNNER_BLAS_THREADS` threads, 1 unless set.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import threadpool_limits

from .errors import UserError

log = logging.getLogger(__name__)

ENV = "LABRUNNER_BLAS_THREADS"
DEFAULT = 1


def configured_threads() -> int:
    """The thread count for numerical work: `LABRUNNER_BLAS_THREADS`, or 1."""
    raw = os.environ.get(ENV, "").strip()
    if not raw:
        return DEFAULT
    try:
        n = int(raw)
    except ValueError:
        raise UserError(f"{ENV}={raw!r}: expected a whole number of threads (1 or more)") from None
    if n < 1:
        raise UserError(f"{ENV}={raw!r}: expected a whole number of threads (1 or more)")
    return n


@contextmanager
def analysis_threads(n: int | None = None) -> Iterator[int]:
    """Run the body with BLAS and OpenMP pools limited to `n` threads (default: `configured_threads()`).

    Restores the previous limits on exit, so a library caller's own setting survives a fit."""
    n = configured_threads() if n is None else n
    with threadpool_limits(limits=n):
        log.debug("numerical work on %d thread(s)", n)
        yield n
