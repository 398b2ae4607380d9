"""Helpers for campaign tests: a tiny procedure and the CLI in a subprocess."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

TINY = """\
name: tiny
temperatures: {list_c: [15, 35], order: serpentine}
soak: {tolerance_c: 0.5, stable_window_s: 120, max_wait_s: 7200, on_timeout: continue, sensor: imu, poll_s: 30}
orientations: [x_up, x_down, y_up, y_down, z_up, z_down]
remount_s: 60
rates: {list_dps: [-50, 0, 50]}
settle_s: 1
record_s: 4
record_poll_s: 2
fit: {run: false}
"""


@pytest.fixture
def tiny(tmp_path):
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY)
    return path


def cli(*args, env=None, timeout=300, check=None):
    """Run `labrunner ARGS` in a subprocess; returns the CompletedProcess."""
    full_env = dict(os.environ)
    full_env.update(env or {})
    proc = subprocess.run([sys.executable, "-m", "labrunner.cli", *map(str, args)], capture_output=True, text=True,
                          env=full_env, timeout=timeout)
    if check is not None:
        assert proc.returncode == check, proc.stderr[-3000:]
    return proc


def crashing_cli(at, *args, timeout=300):
    """Run `labrunner ARGS` in a subprocess that SIGKILLs itself at `at` ("record:N" or "commit:N",
    see crashing_cli.py)."""
    return subprocess.run([sys.executable, str(Path(__file__).with_name("crashing_cli.py")), at, *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)


def popen(*args, env=None):
    full_env = dict(os.environ)
    full_env.update(env or {})
    return subprocess.Popen([sys.executable, "-m", "labrunner.cli", *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=full_env)


ROOT = Path(__file__).resolve().parents[2]
