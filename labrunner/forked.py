"""Independent parts of one job spread over the machine's cores in forked children (the fit's scoring of
its splits, its figures).

Fork, not spawn: a child starts with the parent's data (records, models, the rows' source), so nothing is
pickled on the way in and nothing (numpy, scipy, matplotlib) is imported again; only each part's result
comes back, pickled through a pipe. A child exits with `os._exit`: nothing it inherited (a store's
connection, a progress bar, buffered output) is closed or flushed by it, and it dies with its parent.
A child that fails or dies has its part run again in this process, so the caller sees the part's own
exception, or its result, as without children. With one process (`LABRUNNER_PROCESSES=1`, one usable
core, no `fork`), every part runs here in order: the same results, as the parts are independent.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import os
import pickle
import signal
import sys
from collections.abc import Callable, Sequence
from typing import TypeVar

from .errors import UserError

log = logging.getLogger(__name__)

ENV = "LABRUNNER_PROCESSES"
_PR_SET_PDEATHSIG = 1

T = TypeVar("T")
R = TypeVar("R")


def configured_processes() -> int:
    """How many processes a job's independent parts may use: `LABRUNNER_PROCESSES`, or the usable cores."""
    raw = os.environ.get(ENV, "").strip()
    if raw:
        try:
            n = int(raw)
        except ValueError:
            n = 0
        if n < 1:
            raise UserError(f"{ENV}={raw!r}: expected a whole number of processes (1 or more)")
        return n
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def can_fork() -> bool:
    # macOS forks, but its system libraries are not fork-safe once threads ran: children only on Linux.
    return hasattr(os, "fork") and sys.platform.startswith("linux")


def balanced_groups(weights: Sequence[float], n: int) -> list[list[int]]:
    """Indices 0 .. len(weights)-1 in at most `n` groups of similar total weight (heaviest first, each to
    the lightest group), each group in ascending order; empty groups are left out."""
    groups: list[list[int]] = [[] for _ in range(max(1, n))]
    totals = [0.0] * len(groups)
    for i in sorted(range(len(weights)), key=lambda i: -weights[i]):
        g = totals.index(min(totals))
        groups[g].append(i)
        totals[g] += float(weights[i])
    return [sorted(g) for g in groups if g]


def fork_map(fn: Callable[[T], R], items: Sequence[T], processes: int | None = None) -> list[R]:
    """[fn(x) for x in items], the first item here and each other in a forked child, all at once.

    The caller groups its work into at most `processes` items (`balanced_groups`); `fn` must not rely on
    what another item's call changes in memory (a child's changes stay in the child: it returns them)."""
    n = configured_processes() if processes is None else processes
    if len(items) < 2 or n < 2 or not can_fork():
        return [fn(x) for x in items]
    children: list[tuple[int, int] | None] = []
    gc.freeze()  # the inherited objects stay out of the children's collections: their pages are not copied
    try:
        for x in items[1:]:
            children.append(_start(fn, x))
    finally:
        gc.unfreeze()
    try:
        out: list[R] = [fn(items[0])]
        for i, x in enumerate(items[1:]):
            child, children[i] = children[i], None
            got = _collect(child) if child is not None else None
            # Failed or died there: run here, where its own error (if it has one) is raised.
            out.append(fn(x) if got is None else got[0])  # type: ignore[arg-type]
        return out
    finally:
        for child in children:
            if child is not None:
                _kill(child)


def _start(fn: Callable[[T], R], x: T) -> tuple[int, int] | None:
    read_end, write_end = os.pipe()
    try:
        pid = os.fork()
    except OSError as exc:
        log.warning("no worker process (%s): the part runs in this process", exc)
        os.close(read_end)
        os.close(write_end)
        return None
    if pid == 0:  # the child: never returns
        os.close(read_end)
        _child(fn, x, write_end)
    os.close(write_end)
    return pid, read_end


def _child(fn: Callable[[T], R], x: T, fd: int) -> None:
    code = 1
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops its children itself
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the sequencer's safe-stop handler
        try:
            ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):
            pass
        if os.getppid() == 1:  # the parent died before the line above
            os._exit(1)
        payload = pickle.dumps((fn(x),), protocol=pickle.HIGHEST_PROTOCOL)
        view = memoryview(payload)
        while view:
            view = view[os.write(fd, view):]
        code = 0
    except BaseException as exc:  # the parent runs the part again and meets the error itself
        try:
            log.debug("worker process %d: %s: %s", os.getpid(), type(exc).__name__, exc)
        except BaseException:
            pass
    finally:
        os._exit(code)


def _collect(child: tuple[int, int]) -> tuple[object] | None:
    """The child's result, (value,), or None when it failed, died or sent something unreadable."""
    pid, fd = child
    parts = []
    try:
        while True:
            chunk = os.read(fd, 1 << 20)
            if not chunk:
                break
            parts.append(chunk)
    finally:
        os.close(fd)
    _, status = os.waitpid(pid, 0)
    if not os.WIFEXITED(status) or os.WEXITSTATUS(status) != 0:
        why = f"signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status) else f"exit {os.WEXITSTATUS(status)}"
        log.info("worker process %d ended (%s): its part runs in this process", pid, why)
        return None
    try:
        got = pickle.loads(b"".join(parts))
    except Exception as exc:
        log.warning("worker process %d sent an unreadable result (%s): its part runs in this process", pid, exc)
        return None
    return got if isinstance(got, tuple) and len(got) == 1 else None


def _kill(child: tuple[int, int]) -> None:
    pid, fd = child
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    try:
        os.close(fd)
    except OSError:
        pass
    try:
        os.waitpid(pid, 0)
    except ChildProcessError:
        pass
