"""Start-up cost: building the command line (`labrunner --help`, `status`, `list`, and every command before
its handler runs) loads no analysis, store or simulation module; each handler imports its own when it runs.
A profile of a dry run once showed 28 % of the main thread's samples in start-up imports."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# What building the parser must not load: the brief's list, and the other heavy layers behind the API.
HEAVY = ("scipy", "matplotlib", "pandas", "numpy", "sqlalchemy", "transitions", "pymodbus", "serial",
         "labrunner.calibration", "labrunner.discrepancy", "labrunner.api", "labrunner.store", "labrunner.sims",
         "labrunner.imu", "labrunner.runner", "labrunner.sequencer")


def _loaded_after(code: str) -> list[str]:
    """The heavy modules a fresh interpreter holds after running `code` (a subprocess: this one has them all)."""
    probe = (f"import json, sys\n{code}\n"
             f"print(json.dumps(sorted(m for m in sys.modules if m.startswith({HEAVY!r}))))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    return list(json.loads(out.stdout.strip().splitlines()[-1]))


def _is_heavy(module: str) -> bool:
    return any(module == h or module.startswith(h + ".") for h in HEAVY)


def test_building_the_parser_loads_no_heavy_module() -> None:
    loaded = _loaded_after("import labrunner.cli; labrunner.cli.build_parser()")
    assert [m for m in loaded if _is_heavy(m)] == []


@pytest.mark.parametrize("argv", [["--help"], ["status", "--help"], ["fit", "--help"], ["diagnose", "--help"],
                                  ["--version"]])
def test_help_loads_no_heavy_module(argv: list[str]) -> None:
    loaded = _loaded_after(f"import labrunner.cli\ntry:\n    labrunner.cli.main({argv!r})\nexcept SystemExit:\n"
                           "    pass")
    assert [m for m in loaded if _is_heavy(m)] == []


def test_the_probe_sees_a_heavy_import() -> None:
    """The checks above can fail: the modules a handler imports (here `fit`'s and `diagnose`'s) do load them."""
    loaded = _loaded_after("import labrunner.calibration.command, labrunner.discrepancy.command")
    assert {"scipy", "pandas", "labrunner.calibration.rbf", "labrunner.discrepancy.diagnose"} <= set(loaded)


def test_written_out_names_match_the_analysis() -> None:
    """The parser's copies of the analysis's names (help texts and defaults) are the analysis's."""
    from labrunner.calibration.evaluation import SPLITS
    from labrunner.calibration.rbf_model import VARIANTS
    from labrunner.commands import diagnose, fit
    from labrunner.discrepancy.terms import CAUSE_ORDER

    assert fit.VARIANTS == VARIANTS
    assert fit.SPLITS == SPLITS
    assert diagnose.CAUSE_ORDER == CAUSE_ORDER
