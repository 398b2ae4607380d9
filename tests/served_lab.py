"""`labrunner sim serve` in its own process, and a `labrunner` command run against it with an operator who
presses Enter at each prompt once it is shown: for the tests that rehearse a lab over its configuration."""

import json
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path


def serve(lab_yaml: Path, *args: object, env: Mapping[str, str] | None = None) -> tuple[subprocess.Popen, dict]:
    """Start the servers, writing their lab configuration to `lab_yaml`; returns once they report ready,
    with what they reported (the instruments' addresses). Stop with `stop`."""
    proc = subprocess.Popen([sys.executable, "-m", "labrunner.cli", "sim", "serve", "--lab-config", str(lab_yaml),
                             *map(str, args)], stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.strip().startswith("ready "):
            return proc, json.loads(line.split("ready ", 1)[1])
    proc.wait(10)
    raise AssertionError(f"sim serve did not report ready (exit {proc.returncode})")


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    proc.wait(10)


def run_answering(*args: object, timeout: float, env: Mapping[str, str] | None = None) -> tuple[int, str]:
    """`labrunner ARGS` with Enter pressed at each '>>> Press Enter' prompt once it is shown; its exit code
    and stderr."""
    p = subprocess.Popen([sys.executable, "-m", "labrunner.cli", *map(str, args)], stdin=subprocess.PIPE,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    assert p.stdin is not None and p.stderr is not None
    err = []
    for line in p.stderr:
        err.append(line)
        if line.startswith(">>> Press Enter"):
            p.stdin.write("\n")
            p.stdin.flush()
    p.wait(timeout)
    return p.returncode, "".join(err)
