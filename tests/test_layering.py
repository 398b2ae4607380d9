"""The import contract: which room of labrunner may import which (docs/design.md, "Rooms").

Walks every module's imports (top-level and inside functions) with `ast`, so it sees the
installed layout (`labrunner.drivers` is the repository's drivers/, `labrunner.sims` its
sims/) without importing anything.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# package -> folder, as pyproject.toml's [tool.setuptools.package-dir]
PACKAGE_DIRS = {"labrunner": "labrunner", "labrunner.drivers": "drivers", "labrunner.sims": "sims"}

# Each module belongs to the room of its longest listed prefix.
ROOMS: dict[str, str] = {
    "labrunner.domain": "base",
    "labrunner.clock": "base",
    "labrunner.errors": "base",
    "labrunner.imu": "base",
    "labrunner.drivers": "drivers",
    "labrunner.sims": "sims",
    "labrunner.calibration": "analysis",
    "labrunner.discrepancy": "analysis",
    "labrunner.calibration.command": "command",
    "labrunner.discrepancy.command": "command",
    "labrunner.sequencer": "orchestration",
    "labrunner.runner": "orchestration",
    "labrunner.store": "store",
    "labrunner.procedure": "orchestration",
    "labrunner.ramp_plan": "orchestration",  # the steps of a ramp campaign (procedure.py expands them)
    "labrunner.yaml_config": "base",
    "labrunner.campaign_csv": "store",
    "labrunner.data_source": "store",
    "labrunner.campaign_fit": "orchestration",
    "labrunner.campaign_analysis": "orchestration",
    "labrunner.database": "orchestration",
    "labrunner.report_html": "orchestration",  # reads the store, draws with the analysis's figures
    "labrunner.fault_plan": "orchestration",
    "labrunner.lab": "composition",
    "labrunner.lab_ping": "composition",
    "labrunner.operator": "composition",  # the console operator of a real lab
    "labrunner.api": "composition",
    "labrunner.campaign_session": "composition",
    "labrunner.campaign_abort": "composition",
    "labrunner.sim_config": "composition",
    "labrunner.run_validation": "composition",  # what a run refuses at its start; check and run call it
    "labrunner.commands": "command",
    "labrunner.cli": "command",
    "labrunner.__main__": "command",
    "labrunner.logs": "base",
    "labrunner.fault_kinds": "base",
    "labrunner.version": "base",
    "labrunner.output_paths": "base",
    "labrunner.store_address": "base",
    "labrunner.blas_threads": "base",  # threadpoolctl limits for the fits and the diagnosis
    "labrunner.forked": "base",  # independent parts of a fit in forked children
    "labrunner": "composition",  # the package's __init__: the public Python API
}

# room -> rooms it may import. The instrument interfaces (drivers.protocols, drivers.errors) are
# open to the orchestration: it talks to instruments only through them.
ALLOWED: dict[str, set[str]] = {
    "base": {"base"},
    "drivers": {"base", "drivers", "interfaces"},
    "sims": {"base", "drivers", "interfaces", "sims"},
    "store": {"base", "store"},
    "analysis": {"base", "store", "analysis"},
    "orchestration": {"base", "store", "analysis", "orchestration", "interfaces"},
    "composition": {"base", "store", "analysis", "orchestration", "interfaces", "drivers", "sims", "composition"},
    "command": {"base", "store", "analysis", "orchestration", "interfaces", "drivers", "sims", "composition",
                "command"},
}
INTERFACES = ("labrunner.drivers.protocols", "labrunner.drivers.errors")


def _modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for package, folder in PACKAGE_DIRS.items():
        base = ROOT / folder
        for path in base.rglob("*.py"):
            rel = path.relative_to(base).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            if any(p in PACKAGE_DIRS.get(package, "") for p in ()):
                continue
            name = ".".join([package, *parts])
            if package == "labrunner" and parts and f"labrunner.{parts[0]}" in PACKAGE_DIRS:
                continue
            out[name] = path
    return out


def room_of(module: str) -> str | None:
    best = None
    for prefix in ROOMS:
        if module == prefix or module.startswith(prefix + "."):
            if best is None or len(prefix) > len(best):
                best = prefix
    if best is None:
        return None
    if module.startswith(INTERFACES):
        return "interfaces"
    return ROOMS[best]


def _imports(module: str, path: Path) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_pkg else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append((node.lineno, target))
            out += [(node.lineno, f"{target}.{a.name}") for a in node.names]
    return [(line, t) for line, t in out if t == "labrunner" or t.startswith("labrunner.")]


MODULES = _modules()


def test_every_module_has_a_room() -> None:
    missing = sorted(m for m in MODULES if room_of(m) is None)
    assert not missing, f"modules without a room (add them to ROOMS in {Path(__file__).name}): {missing}"


def test_the_layout_is_walked() -> None:
    # The walk must see all three folders, or the contract below checks nothing.
    assert {"labrunner.sequencer", "labrunner.drivers.protocols", "labrunner.sims.world"} <= set(MODULES)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_respect_the_rooms(module: str) -> None:
    src = room_of(module)
    assert src is not None
    bad = []
    for line, target in _imports(module, MODULES[module]):
        if target not in MODULES and target.rsplit(".", 1)[0] in MODULES:
            target = target.rsplit(".", 1)[0]  # `from package import name`: the package is imported
        dst = room_of(target)
        allowed = ALLOWED["drivers"] if src == "interfaces" else ALLOWED.get(src, set())
        if dst is None or dst == src or dst in allowed:
            continue
        bad.append(f"{MODULES[module].relative_to(ROOT)}:{line}: {module} ({src}) imports {target} ({dst})")
    assert not bad, "\n".join(bad)


def test_the_contract_can_fail() -> None:
    # A seeded violation is caught: the checker is not vacuous.
    assert room_of("labrunner.sims.world") not in ALLOWED["analysis"]
    assert room_of("labrunner.drivers.rate_table") not in ALLOWED["orchestration"]
    assert room_of("labrunner.drivers.protocols") in ALLOWED["orchestration"]
