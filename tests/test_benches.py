"""Every script in bench/ parses its options: `--help` exits 0 and says how to run it (issue 15, target 6)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "bench"
SCRIPTS = sorted(p for p in BENCH.glob("*.py") if p.name != "common.py")  # every script; common is a module


def test_every_bench_answers_help() -> None:
    assert len(SCRIPTS) >= 8, SCRIPTS
    # All at once: each pays its imports (pandas, scipy) and the machine has two cores.
    procs = {p.name: subprocess.Popen([sys.executable, str(p), "--help"], stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, cwd=BENCH.parent) for p in SCRIPTS}
    failed = []
    for name, proc in procs.items():
        try:
            out, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            failed.append(f"{name}: --help did not finish in 120 s")
            continue
        if proc.returncode != 0 or "usage:" not in out:
            failed.append(f"{name}: exit {proc.returncode}: {err.strip()[-500:]}")
    assert not failed, "\n".join(failed)
