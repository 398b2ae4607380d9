"""What every bench in bench/ shares: a CPU hog, child-process measurement, the load and one report line.

    from bench.common import cpu_hog, report, run_measured, call_measured, load_average

`run_measured(cmd)` runs a command and `call_measured(fn, *args)` a Python callable, each in a child
process, and give its wall time, CPU time (user + sys) and peak RSS, measured by the kernel for that
child alone (`os.wait4`; `getrusage(RUSAGE_CHILDREN)` would give the largest of all children so far).
`report(...)` prints "name: value unit (limit L, ratio R, OK|MISSED)", the line issue 15 asks of
every bench. `cpu_hog()` keeps one core busy in a second process while its block runs (issue 15,
target 5: each bench runs once on a quiet and once on a busy machine).
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import pickle
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

_HOG_CODE = "while True:\n    pass\n"
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In the child before exec: SIGKILL when the bench dies, so a killed bench leaves no hog spinning."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux: the finally below still kills it
        pass


@contextlib.contextmanager
def cpu_hog(enabled: bool = True) -> Iterator[int | None]:
    """A second process spinning on one core while the block runs; yields its pid (None when disabled).

    Killed (SIGKILL) and reaped on leaving the block, also on an exception; it also dies with this
    process if this process is killed."""
    if not enabled:
        yield None
        return
    hog = subprocess.Popen([sys.executable, "-c", _HOG_CODE], stdin=subprocess.DEVNULL,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=_die_with_parent)
    log.info("cpu hog started: pid %d", hog.pid)
    try:
        yield hog.pid
    finally:
        hog.kill()
        hog.wait()
        log.info("cpu hog %d stopped", hog.pid)


def load_average() -> tuple[float, float, float]:
    """The 1, 5 and 15 minute load averages (quoted beside every timing on the shared machine)."""
    return os.getloadavg()


def load_line() -> str:
    one, five, fifteen = load_average()
    return f"load average {one:.2f}, {five:.2f}, {fifteen:.2f} ({os.cpu_count()} cores)"


@dataclass(frozen=True)
class Measured:
    """A child process's cost as the kernel counted it."""

    wall_s: float
    user_s: float
    sys_s: float
    peak_rss_bytes: int
    returncode: int
    # The largest proportional set size (PSS) of the command's process tree seen, sampled every 0.2 s:
    # the memory it took from the machine when it forks children (their shared pages counted once; the
    # kernel's peak RSS above is the largest single process's). 0: not sampled.
    peak_tree_pss_bytes: int = 0

    @property
    def cpu_s(self) -> float:
        return self.user_s + self.sys_s

    @property
    def peak_rss_mb(self) -> float:
        return self.peak_rss_bytes / 1e6

    def line(self) -> str:
        pss = f", process tree peak PSS {self.peak_tree_pss_bytes / 1e6:,.0f} MB" if self.peak_tree_pss_bytes else ""
        return (f"wall {self.wall_s:.2f} s, CPU {self.cpu_s:.2f} s (user {self.user_s:.2f}, sys {self.sys_s:.2f}), "
                f"peak RSS {self.peak_rss_mb:,.0f} MB{pss}")


def _measured(start: float, status: int, usage: Any) -> Measured:
    return Measured(wall_s=time.perf_counter() - start, user_s=usage.ru_utime, sys_s=usage.ru_stime,
                    peak_rss_bytes=int(usage.ru_maxrss) * 1024,  # Linux: kilobytes
                    returncode=os.waitstatus_to_exitcode(status))


@dataclass(frozen=True)
class CommandRun:
    measured: Measured
    stdout: str
    stderr: str
    killed_for_memory: bool = False  # the tree's RSS passed `memory_limit_bytes` and it was killed


def _tree(pid: int) -> list[int]:
    """`pid` and its descendants (from /proc's children lists)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        try:
            for task in Path(f"/proc/{p}/task").iterdir():
                todo.extend(int(c) for c in (task / "children").read_text().split())
        except OSError:  # gone meanwhile
            continue
    return out


def tree_rss_bytes(pid: int) -> int:
    """Resident memory of `pid` and its descendants now (VmRSS summed; 0 for those gone)."""
    total = 0
    for p in _tree(pid):
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) * 1024
        except OSError:
            continue
    return total


def tree_pss_bytes(pid: int, *, with_root: bool = True) -> int:
    """Proportional set size of `pid` (unless not `with_root`) and its descendants now (Pss from
    smaps_rollup summed: pages shared by n of them count 1/n in each; 0 for those gone)."""
    total = 0
    for p in _tree(pid)[0 if with_root else 1:]:
        try:
            for line in Path(f"/proc/{p}/smaps_rollup").read_text().splitlines():
                if line.startswith("Pss:"):
                    total += int(line.split()[1]) * 1024
                    break
        except OSError:
            continue
    return total


def _pss_sampler(pid: int, stop: threading.Event, peak: list[int]) -> None:
    while not stop.wait(0.2):
        peak[0] = max(peak[0], tree_pss_bytes(pid, with_root=False))  # the command's tree, not the launcher


def _memory_guard(pid: int, limit: int, stop: threading.Event, tripped: threading.Event) -> None:
    """Kill the process tree of `pid` when its RSS passes `limit` (the machine is shared: no OOM)."""
    while not stop.wait(0.25):
        if tree_rss_bytes(pid) > limit:
            tripped.set()
            for p in reversed(_tree(pid)[1:]):  # the command (and its children), not the launcher
                with contextlib.suppress(OSError):
                    os.kill(p, signal.SIGKILL)
            return


# The command is started by a small launcher process, not by this one: a child's peak RSS counts what
# the process that forked it held (Linux keeps the pre-exec high-water mark, and subprocess's vfork
# shares the parent's memory), so a bench holding a synthesized campaign would inflate every figure.
_LAUNCHER = """\
import json, os, sys
pid = os.posix_spawnp(sys.argv[2], sys.argv[2:], os.environ)
_, status, ru = os.wait4(pid, 0)
with open(sys.argv[1], "w") as f:
    json.dump([status, ru.ru_utime, ru.ru_stime, ru.ru_maxrss], f)
"""


def run_measured(cmd: Sequence[str | Path], *, cwd: str | Path | None = None, env: dict[str, str] | None = None,
                 memory_limit_bytes: int | None = None) -> CommandRun:
    """Run `cmd` to its end in a child process; its wall, CPU and peak RSS (the child and the children it
    waited for), and its output. A non-zero exit is returned, not raised: the caller names the failure.
    With `memory_limit_bytes` the command is killed when its resident memory passes it."""
    with tempfile.TemporaryDirectory(prefix="bench-run-") as tmp:
        usage_file = Path(tmp) / "usage.json"
        out_file, err_file = Path(tmp) / "stdout", Path(tmp) / "stderr"
        with out_file.open("wb") as out, err_file.open("wb") as err:
            start = time.perf_counter()
            proc = subprocess.Popen([sys.executable, "-S", "-c", _LAUNCHER, str(usage_file), *map(str, cmd)],
                                    cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                    preexec_fn=_die_with_parent)
            stop, tripped = threading.Event(), threading.Event()
            guard = threading.Thread(target=_memory_guard, args=(proc.pid, memory_limit_bytes, stop, tripped),
                                     daemon=True) if memory_limit_bytes else None
            if guard:
                guard.start()
            pss = [0]
            sampler = threading.Thread(target=_pss_sampler, args=(proc.pid, stop, pss), daemon=True)
            sampler.start()
            try:
                launcher_rc = proc.wait()
            except BaseException:
                for p in reversed(_tree(proc.pid)):
                    with contextlib.suppress(OSError):
                        os.kill(p, signal.SIGKILL)
                proc.wait()
                raise
            finally:
                stop.set()
                if guard:
                    guard.join()
                sampler.join()
            wall = time.perf_counter() - start
        stdout = out_file.read_bytes().decode(errors="replace")
        stderr = err_file.read_bytes().decode(errors="replace")
        if launcher_rc != 0 or not usage_file.exists():
            # the launcher itself failed: the command could not be started (not found, not executable)
            raise RuntimeError(f"cannot run {' '.join(map(str, cmd))}: {stderr.strip().splitlines()[-1:]}")
        status, user, system, maxrss_kb = json.loads(usage_file.read_text())
    measured = Measured(wall_s=wall, user_s=user, sys_s=system, peak_rss_bytes=int(maxrss_kb) * 1024,
                        returncode=os.waitstatus_to_exitcode(status), peak_tree_pss_bytes=pss[0])
    return CommandRun(measured, stdout, stderr, tripped.is_set())


class ChildFailed(RuntimeError):
    """The callable raised in the child process (its traceback is the message)."""


def call_measured(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[Any, Measured]:
    """Call `fn(*args, **kwargs)` in a forked child process; its (picklable) result and its cost.

    The child's peak RSS includes what it inherited from this process at the fork (counted as it is
    touched): call it before this process grows, or compare against a baseline call."""
    read_fd, write_fd = os.pipe()
    start = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # the child: run, send (ok, value) back, and leave without running the parent's cleanup
        os.close(read_fd)
        code = 0
        try:
            payload = pickle.dumps((True, fn(*args, **kwargs)))
        except BaseException:
            payload = pickle.dumps((False, traceback.format_exc()))
            code = 1
        with os.fdopen(write_fd, "wb") as w:
            w.write(payload)
        os._exit(code)
    os.close(write_fd)
    try:
        with os.fdopen(read_fd, "rb") as r:
            data = r.read()
        _, status, usage = os.wait4(pid, 0)
    except BaseException:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        raise
    measured = _measured(start, status, usage)
    if not data:
        raise ChildFailed(f"the child process died without a result (exit {measured.returncode})")
    ok, value = pickle.loads(data)
    if not ok:
        raise ChildFailed(value)
    return value, measured


def peak_rss_of(cmd: Sequence[str | Path]) -> int:
    """Peak RSS in bytes of `cmd` run to its end (raises if it fails)."""
    run = run_measured(cmd)
    if run.measured.returncode != 0:
        raise RuntimeError(f"{' '.join(map(str, cmd))} exited {run.measured.returncode}: {run.stderr[-2000:]}")
    return run.measured.peak_rss_bytes


@dataclass(frozen=True)
class Result:
    """One measured figure against its target."""

    name: str
    value: float
    limit: float
    unit: str
    lower_is_better: bool = True

    @property
    def ratio(self) -> float:
        """value/limit when lower is better, limit/value otherwise: <= 1 meets the target either way."""
        if self.lower_is_better:
            if not self.limit:  # a limit of zero (rows lost): met exactly or not at all
                return 0.0 if self.value <= 0 else float("inf")
            return self.value / self.limit
        return self.limit / self.value if self.value else float("inf")

    @property
    def ok(self) -> bool:
        return self.value <= self.limit if self.lower_is_better else self.value >= self.limit

    def line(self, width: int = 34) -> str:
        bound = "limit" if self.lower_is_better else "at least"
        return (f"{self.name + ':':{width}s} {_num(self.value)} {self.unit} ({bound} {_num(self.limit)}, "
                f"ratio {self.ratio:.2f}, {'OK' if self.ok else 'MISSED'})")


def _num(v: float) -> str:
    if v != v or v in (float("inf"), float("-inf")):
        return str(v)
    a = abs(v)
    if a >= 1e5:
        return f"{v:,.0f}"
    if a >= 100:
        return f"{v:.0f}"
    if a >= 10:
        return f"{v:.1f}"
    return f"{v:.3g}"


def report(name: str, value: float, limit: float, unit: str, lower_is_better: bool = True) -> Result:
    """Print the target line of one figure and return it (benches collect them for their summary)."""
    result = Result(name, value, limit, unit, lower_is_better)
    print(result.line(), flush=True)
    return result


def available_memory_bytes() -> int:
    """MemAvailable from /proc/meminfo (what can be had without swapping), or 0 where it is not known."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0
