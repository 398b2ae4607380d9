"""A command whose standard output the shell closed (`labrunner export ... --csv - >&-`) ends as on a closed
pipe, not in a traceback: Python sets sys.stdout to None then, and the CLI's last flush met None."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from labrunner.cli import EXIT_BROKEN_PIPE

ROOT = Path(__file__).resolve().parents[1]


def _closed_stdout(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrunner.cli", *args], cwd=ROOT, stderr=subprocess.PIPE,
                          text=True, preexec_fn=lambda: os.close(1), timeout=120)


def test_writing_to_a_closed_stdout_is_a_closed_pipe():
    p = _closed_stdout("check", str(ROOT / "procedures" / "quick.yaml"))
    assert p.returncode == EXIT_BROKEN_PIPE, p.stderr
    assert "Traceback" not in p.stderr and p.stderr == ""


def test_a_command_that_writes_nothing_runs_with_stdout_closed(tmp_path):
    p = _closed_stdout("status", str(tmp_path / "none.db"))  # its error goes to stderr, named
    assert "Traceback" not in p.stderr
    assert "none.db" in p.stderr and p.returncode not in (0, EXIT_BROKEN_PIPE)
