"""The package installs cleanly beside others: one top-level package (`labrunner`, with the repository's
drivers/, sims/ and procedures/ inside it), the shipped procedures as package data, and a built wheel
installed into a fresh venv runs the quick dry run from an unrelated directory."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from labrunner.procedure import load_procedure, shipped_procedures
from labrunner.yaml_config import ConfigError

ROOT = Path(__file__).resolve().parents[1]  # the checkout under test
SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
# What a copy of the checkout leaves out: VCS, environments, build output, run artefacts.
NOT_SOURCE = shutil.ignore_patterns(".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache",
                                    ".hypothesis", "*.db", "*.db-wal", "*.db-shm", "out")


def _package_folders() -> dict[str, Path]:
    """Every package in the tree, by its installed name (package-dir maps the top-level folders)."""
    found: dict[str, Path] = {}
    for package, folder in SETUPTOOLS["package-dir"].items():
        base = ROOT / folder
        for init in base.rglob("__init__.py"):
            rel = init.parent.relative_to(base)
            found[".".join([package, *rel.parts])] = init.parent
    return found


def test_every_package_folder_is_installed() -> None:
    # The package list is explicit (package-dir needs it): a new subpackage must be added to it.
    listed = set(SETUPTOOLS["packages"])
    found = set(_package_folders())
    assert found - listed == set(), f"add to [tool.setuptools] packages in pyproject.toml: {sorted(found - listed)}"
    assert listed - found == set(), f"listed but not in the tree: {sorted(listed - found)}"
    assert not any(name.split(".")[0] != "labrunner" for name in listed)


def test_shipped_procedures_load_by_name_from_any_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert {"quick", "paper_campaign"} <= set(shipped_procedures())
    for name in ("quick", "quick.yaml"):
        proc = load_procedure(name)
        assert proc.name == "quick" and Path(proc.source).name == "quick.yaml"
        assert proc.text == (ROOT / "procedures" / "quick.yaml").read_text()
    # A file of that name in the working directory wins over the shipped one.
    (tmp_path / "quick.yaml").write_text((ROOT / "procedures" / "quick.yaml").read_text().replace(
        "name: quick", "name: my_quick"))
    assert load_procedure("quick.yaml").name == "my_quick"


def test_missing_procedure_names_the_shipped_ones(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    for missing in ("nonesuch", "elsewhere/quick.yaml"):  # a path with folders is never a shipped name
        with pytest.raises(ConfigError) as err:
            load_procedure(missing)
        assert str(err.value) == (f"{Path(missing)}: file not found (shipped procedures, usable by name: "
                                  f"{', '.join(shipped_procedures())})")


def _run(cmd: list[str | Path], **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True, stdin=subprocess.DEVNULL,
                          **kw)  # type: ignore[call-overload]


@pytest.mark.slow
def test_built_wheel_installs_alone_and_runs_the_quick_dry_run(tmp_path: Path) -> None:
    # Build from a copy, so setuptools' build/ and egg-info never land in (or come from) the checkout.
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=NOT_SOURCE)
    wheels = tmp_path / "wheels"
    built = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", wheels, src], timeout=300)
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = wheels.glob("labrunner-*.whl")

    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        dist_info = next(n.split("/")[0] for n in names if n.endswith(".dist-info/RECORD"))
        record = zf.read(f"{dist_info}/RECORD").decode()
        top_level = zf.read(f"{dist_info}/top_level.txt").decode().split()
    assert {n.split("/")[0] for n in names} == {"labrunner", dist_info}
    assert top_level == ["labrunner"]
    for shipped in ("quick.yaml", "paper_campaign.yaml"):
        assert f"labrunner/procedures/{shipped},sha256=" in record
    # Every module of the tree is in the wheel, at its installed name.
    for package, folder in _package_folders().items():
        for module in folder.glob("*.py"):
            assert f"{package.replace('.', '/')}/{module.name}" in names

    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    venv = tmp_path / "venv"
    made = _run([sys.executable, "-m", "venv", venv], timeout=120, env=env)
    assert made.returncode == 0, made.stderr[-3000:]
    py, cli = venv / "bin" / "python", venv / "bin" / "labrunner"
    # Dependencies come from the package index: skip (with the reason) only if it cannot be reached at
    # all, probed with one small dependency; any other install failure is a failure of the package.
    probe = _run([py, "-m", "pip", "download", "--quiet", "--no-input", "--no-deps", "-d", tmp_path / "probe",
                  "pyserial>=3.5,<4"], timeout=300, env=env)
    if probe.returncode != 0:
        reason = (probe.stderr.strip().splitlines() or ["no output"])[-1]
        pytest.skip(f"the package index is unreachable, dependencies cannot be installed: {reason}")
    installed = _run([py, "-m", "pip", "install", "--quiet", "--no-input", wheel], timeout=600, env=env)
    assert installed.returncode == 0, installed.stderr[-3000:]

    work = tmp_path / "elsewhere"  # not the checkout: only the installed package can be found
    work.mkdir()
    probe = _run([py, "-c", "import importlib.resources as r, importlib.util as u; "
                  "print(u.find_spec('drivers'), u.find_spec('sims'), "
                  "(r.files('labrunner.procedures') / 'quick.yaml').is_file(), "
                  "u.find_spec('labrunner').origin)"], cwd=work, env=env, timeout=60)
    assert probe.returncode == 0, probe.stderr
    no_drivers, no_sims, has_quick, origin = probe.stdout.split()
    assert (no_drivers, no_sims, has_quick) == ("None", "None", "True")
    assert origin.startswith(str(venv))  # the installed copy, not the checkout

    check = _run([cli, "check", "quick"], cwd=work, env=env, timeout=120)
    assert check.returncode == 0, check.stderr
    assert "procedure 'quick' is valid" in check.stdout
    run = _run([cli, "run", "quick", "--sim", "--db", "run.db", "--quiet"], cwd=work, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "done. 192/192 steps recorded" in run.stderr
    models = work / "run_fit" / "campaign-1"  # each campaign's end-of-run fit in its own directory
    assert {"polynomial.json", "rbf.json", "imu_calibration.h"} <= {p.name for p in models.iterdir()}
    assert (work / "run.db").stat().st_size > 0
