"""bench/common.py: the hog is started and killed, child costs are the child's, the report line."""

from __future__ import annotations

import os
import sys
import time

import pytest

from bench.common import ChildFailed, Result, call_measured, cpu_hog, load_average, report, run_measured


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_hog_spins_and_is_killed_also_on_an_exception() -> None:
    with pytest.raises(RuntimeError, match="boom"):
        with cpu_hog() as pid:
            assert pid is not None
            t0 = os.times()
            time.sleep(0.6)
            # the hog burns CPU: its /proc stat shows user time growing (not this process's)
            ticks = int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[11])
            assert ticks > 0
            assert os.times().user - t0.user < 0.3
            raise RuntimeError("boom")
    assert not _alive(pid)  # reaped: no zombie, no process


def test_disabled_hog_starts_nothing() -> None:
    with cpu_hog(False) as pid:
        assert pid is None


def _allocate(mb: int) -> int:
    block = bytearray(mb * 1024 * 1024)
    block[::4096] = b"x" * len(block[::4096])  # touch every page
    return len(block)


def test_call_measured_counts_the_childs_peak_rss_and_result() -> None:
    small, m_small = call_measured(_allocate, 1)
    big, m_big = call_measured(_allocate, 200)
    assert (small, big) == (1 << 20, 200 << 20)
    # per child, not the largest of all children so far: the small one ran first
    assert m_big.peak_rss_bytes - m_small.peak_rss_bytes > 150e6
    assert m_big.returncode == 0 and m_big.wall_s > 0


def _fail() -> None:
    raise ValueError("bad input")


def test_call_measured_raises_the_childs_error() -> None:
    with pytest.raises(ChildFailed, match="ValueError: bad input"):
        call_measured(_fail)


def test_run_measured_cpu_time_and_exit_code() -> None:
    spin = run_measured([sys.executable, "-c", "import time\nt=time.process_time()\n"
                                               "while time.process_time()-t<0.4: pass\nprint('done')"])
    assert spin.measured.returncode == 0 and spin.stdout.strip() == "done"
    assert spin.measured.cpu_s >= 0.35
    # the child's own memory, not this (large) pytest process's that started it
    ballast = bytearray(200 * 2**20)
    ballast[::4096] = b"x" * len(ballast[::4096])
    small = run_measured([sys.executable, "-c", "pass"])
    assert small.measured.peak_rss_bytes < 100e6, small.measured
    del ballast
    big = run_measured([sys.executable, "-c", "b = bytearray(300 * 2**20); b[::4096] = b'x' * len(b[::4096])"])
    assert big.measured.peak_rss_bytes - spin.measured.peak_rss_bytes > 250e6
    failed = run_measured([sys.executable, "-c", "import sys; sys.exit(3)"])
    assert failed.measured.returncode == 3
    grow = run_measured([sys.executable, "-c", "import time\nb = []\nwhile True:\n"
                                               "    b.append(bytearray(20 * 2**20)); time.sleep(0.02)"],
                        memory_limit_bytes=300 * 2**20)
    assert grow.killed_for_memory and grow.measured.returncode == -9
    assert grow.measured.peak_rss_bytes < 600 * 2**20
    with pytest.raises(RuntimeError, match="cannot run"):
        run_measured(["/nonexistent/labrunner-bench-command"])


def test_report_line_ratio_and_verdict(capsys: pytest.CaptureFixture[str]) -> None:
    r = report("fit peak RSS", 1800.0, 1500.0, "MB")
    assert not r.ok and r.ratio == pytest.approx(1.2)
    line = capsys.readouterr().out.strip()
    assert line.startswith("fit peak RSS:") and line.endswith("(limit 1500, ratio 1.20, MISSED)")
    fast = Result("store writes", 5e6, 4e6, "samples/s", lower_is_better=False)
    assert fast.ok and fast.ratio == pytest.approx(0.8)
    assert "at least 4,000,000" in fast.line()


def test_load_average() -> None:
    one, five, fifteen = load_average()
    assert min(one, five, fifteen) >= 0
