"""The fit's malloc settings (glibc): its threads share an arena, and freed large arrays go back to the system.

Both are process-wide and stay set after the fit (docs/calibration.md, "Memory").
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging

log = logging.getLogger(__name__)

M_ARENA_MAX = -8  # glibc's mallopt parameters
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 1 << 22


@functools.cache
def tuned_malloc() -> None:
    """Let threads allocate from the malloc arenas there are instead of one more each, and return freed large
    arrays to the system (glibc; once per process).

    An arena keeps the memory its threads freed (up to twice the largest array freed, above its top), so
    every worker thread's arena holds tens of MB through the fit: the paper store's fit peaked at 494 MB
    with two training threads against 454 MB on one arena (468 MB single-threaded). Has no effect once
    glibc has settled its arena limit (more than eight arenas), nor beyond glibc."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt(M_ARENA_MAX, 1)
        # A fixed threshold: every array of 4 MB or more is mapped and unmapped, not kept in the heap. glibc's
        # own threshold climbs to the largest array freed (up to 32 MB), and the heap then holds freed chunks
        # of rows: the fit of a 10x paper store peaked at 1.45x the 1x one's PSS, 1.11x with this (1 MB:
        # 1.06x, but twice the system time of the page faults).
        libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    except (OSError, AttributeError):
        log.debug("mallopt not available: threads keep their own malloc arenas")
