"""The command line's own options: `python -m labrunner`, `-v`/`--log-level`, errors without tracebacks."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from labrunner.cli import build_parser, log_level

from .test_api import TINY


def labrunner_m(*args: object, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "labrunner", *map(str, args)], capture_output=True, text=True,
                          timeout=120, cwd=cwd)


@pytest.mark.parametrize(("argv", "level"), [
    ([], "WARNING"), (["-v"], "INFO"), (["-vv"], "DEBUG"), (["-vvv"], "DEBUG"),
    (["--log-level", "error"], "ERROR"), (["-vv", "--log-level", "WARNING"], "WARNING"),
])
def test_log_level_from_flags(argv: list[str], level: str) -> None:
    args = build_parser().parse_args([*argv, "status", "x.db"])
    assert log_level(args) == level


def test_python_m_labrunner_is_the_cli(tmp_path: Path) -> None:
    assert labrunner_m("--version").stdout.startswith("labrunner ")
    proc = labrunner_m("status", tmp_path / "missing.db")
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"labrunner status: error: {tmp_path / 'missing.db'}: database not found"
    assert labrunner_m("--log-level", "LOUD", "status", "x.db").returncode == 2  # argparse: invalid choice


def test_verbose_logs_what_the_run_does_and_quiet_by_default(tmp_path: Path) -> None:
    (tmp_path / "tiny.yaml").write_text(TINY)
    quiet = labrunner_m("run", "tiny.yaml", "--sim", "--db", "a.db", "--quiet", cwd=tmp_path)
    assert quiet.returncode == 0, quiet.stderr[-2000:]
    assert " INFO " not in quiet.stderr and " DEBUG " not in quiet.stderr
    assert "done. 36/36 steps recorded" in quiet.stderr
    loud = labrunner_m("-v", "run", "tiny.yaml", "--sim", "--db", "b.db", "--quiet", cwd=tmp_path)
    assert loud.returncode == 0, loud.stderr[-2000:]
    assert "INFO    labrunner.campaign_session: campaign 1 'tiny' in b.db: 36 steps (sim)" in loud.stderr
    assert " DEBUG " not in loud.stderr
    debug = labrunner_m("--log-level", "DEBUG", "status", "b.db", cwd=tmp_path)
    assert debug.returncode == 0 and "status      done" in debug.stdout
