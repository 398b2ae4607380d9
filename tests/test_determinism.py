"""Deterministic dry runs (issue 13, item 5): the quick procedure on a machine whose cores are all busy gives,
bit for bit, the export (`labrunner export --csv --with-monitor`) and the events of a run on an idle one,
without faults (and then without a single fault event) and with seeded random faults.

Each run is the command line in its own process; the load is busy loops in other processes, one per core,
running through the whole loaded run.
"""

from __future__ import annotations

import multiprocessing as mp
import multiprocessing.synchronize
import os
import re
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from importlib import resources
from pathlib import Path

import pytest
import yaml

from labrunner.procedure import SHIPPED_PACKAGE

SEED = "11"
FAULTS = "12"
_ADDRESS = re.compile(r"socket://127\.0\.0\.1:\d+|127\.0\.0\.1:\d+|/dev/pts/\d+")


def _spin(stop: multiprocessing.synchronize.Event) -> None:
    while not stop.is_set():
        pass


@contextmanager
def cpu_hog() -> Iterator[None]:
    stop = mp.get_context("spawn").Event()
    hogs = [mp.get_context("spawn").Process(target=_spin, args=(stop,), daemon=True)
            for _ in range(os.cpu_count() or 2)]
    for h in hogs:
        h.start()
    try:
        time.sleep(0.5)  # the hogs are spinning before the run starts
        yield
    finally:
        stop.set()
        for h in hogs:
            h.join(5)
            if h.is_alive():
                h.kill()


@pytest.fixture(scope="module")
def procedure(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # The quick procedure without its end-of-run fit (the fit reads what the export compares).
    spec = yaml.safe_load((resources.files(SHIPPED_PACKAGE) / "quick.yaml").read_text(encoding="utf-8"))
    spec["fit"]["run"] = False
    path = tmp_path_factory.mktemp("proc") / "quick_nofit.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def _dry_run(procedure: Path, out: Path, *extra: str) -> tuple[bytes, list[tuple[object, ...]], float]:
    db = out / "run.db"
    t0 = time.monotonic()
    run = subprocess.run([sys.executable, "-m", "labrunner", "run", str(procedure), "--sim", "--seed", SEED,
                          "--db", str(db), *extra], capture_output=True, text=True, timeout=900)
    wall = time.monotonic() - t0
    assert run.returncode == 0, run.stderr[-3000:]
    csv = out / "run.csv"
    export = subprocess.run([sys.executable, "-m", "labrunner", "export", str(db), "--csv", str(csv),
                             "--with-monitor"], capture_output=True, text=True, timeout=300)
    assert export.returncode == 0, export.stderr
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT t_s, kind, state, step_idx, message FROM events ORDER BY id").fetchall()
    # The simulators' ports differ from run to run; everything else must not.
    events = [(t, kind, state, step, _ADDRESS.sub("ADDR", message)) for t, kind, state, step, message in rows]
    return csv.read_bytes(), events, wall


@pytest.mark.timeout(1800)  # four quick dry runs, two of them on a machine made slow on purpose
@pytest.mark.parametrize("extra", [(), ("--faults", FAULTS)], ids=["no-faults", "faults"])
def test_a_loaded_machine_gives_the_idle_machines_dry_run(tmp_path: Path, procedure: Path,
                                                          extra: tuple[str, ...]) -> None:
    (tmp_path / "idle").mkdir()
    (tmp_path / "loaded").mkdir()
    idle_csv, idle_events, idle_wall = _dry_run(procedure, tmp_path / "idle", *extra)
    with cpu_hog():
        loaded_csv, loaded_events, loaded_wall = _dry_run(procedure, tmp_path / "loaded", *extra)
    print(f"{extra or 'no faults'}: idle {idle_wall:.1f} s, loaded {loaded_wall:.1f} s of wall time")
    faults = [e for e in idle_events if e[1] == "fault"]
    if extra:
        assert faults, "the fault plan injected nothing"
    else:
        assert not faults, faults[:3]
    assert len(idle_csv) > 1_000_000
    assert loaded_events == idle_events
    assert loaded_csv == idle_csv
