"""Drivers by name: the entry-point registry, lab configurations naming drivers, and a third-party
driver package installed during the test and found through the `labrunner.drivers` group."""

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from labrunner.clock import VirtualClock
from labrunner.drivers import registry
from labrunner.drivers.builtin import SerialFields
from labrunner.drivers.protocols import RateTable
from labrunner.drivers.rate_table import SerialRateTable
from labrunner.lab import LabConfig, build_drivers, lab_config_from_dict, load_lab_config, resolve_drivers
from labrunner.yaml_config import ConfigError
from tests.served_lab import run_answering, serve, stop

ROOT = Path(__file__).resolve().parents[2]
LAB = {"chamber": {"driver": "watlow_f4", "port": 1502}, "table": {"driver": "ideal_aerosmith", "port": "/dev/null"},
       "imu": {"port": "/dev/null"}}


def test_every_built_in_declared_in_pyproject_is_installed_and_loads():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["entry-points"]["labrunner.drivers"]
    found = registry.installed()
    for name, value in declared.items():
        assert name in found, f"{name} is declared but not installed (pip install -e . again?)"
        assert found[name].source == value and found[name].driver is not None, found[name]
    assert {"watlow_f4", "watlow_f4t", "modbus_chamber", "ideal_aerosmith", "labrunner_table", "serial_table",
            "labrunner_imu"} <= set(declared)
    assert registry.DEFAULTS == {"chamber": "modbus_chamber", "table": "labrunner_table", "imu": "labrunner_imu"}


def test_unknown_and_wrong_kind_drivers_list_what_is_installed():
    with pytest.raises(registry.DriverLookupError,
                       match=r"unknown table driver 'acme'; installed table drivers: .*ideal_aerosmith, "
                             r"labrunner_table, serial_table"):
        registry.lookup("acme", "table")
    with pytest.raises(registry.DriverLookupError, match="driver 'watlow_f4' drives a chamber, not a table"):
        registry.lookup("watlow_f4", "table")


def test_a_lab_configuration_names_its_drivers_and_each_section_is_checked_by_its_driver(tmp_path):
    cfg = lab_config_from_dict(LAB)
    assert [cfg.instrument(k).driver.name for k in ("chamber", "table", "imu")] == [
        "watlow_f4", "ideal_aerosmith", "labrunner_imu"]
    assert cfg.section("chamber").port == 1502
    chamber, table, imu = build_drivers(cfg, VirtualClock(), max_rate_dps=100)
    assert chamber.profile.name == "watlow_f4" and isinstance(table, SerialRateTable)
    assert table.language.name == "ideal_aerosmith" and table.max_rate_dps == 100
    # A driver's own keys: `language` belongs to serial_table, not to ideal_aerosmith (its language is fixed).
    path = tmp_path / "lab.yaml"
    path.write_text("name: x\nchamber:\n  driver: watlow_f5\n  port: 502\n"
                    "table:\n  driver: ideal_aerosmith\n  port: /dev/ttyUSB1\n  language: labrunner\n"
                    "imu: {port: /dev/ttyUSB2, rate_hz: 0}\n")
    with pytest.raises(ConfigError) as err:
        load_lab_config(path)
    assert [m.split(": ", 1) for m in err.value.messages] == [
        [f"{path}:3", "chamber.driver: unknown chamber driver 'watlow_f5'; installed chamber drivers: "
                      "modbus_chamber, watlow_f4, watlow_f4t"],
        [f"{path}:8", "table.language is not a known key"],
        [f"{path}:9", "imu.rate_hz must be in 0.1..10000 Hz, got 0"],
    ], err.value.messages
    # A generic table driver takes its language as configuration.
    cfg = lab_config_from_dict({**LAB, "table": {"driver": "serial_table", "port": "/dev/null",
                                                 "language": {"base": "ideal_aerosmith", "terminator": "\r"}}})
    _, table, _ = build_drivers(cfg, VirtualClock(), max_rate_dps=100)
    assert table.language.terminator == "\r"


class _Half:
    """Has a rate table's attributes but not its methods."""

    name = "half"
    address = "nowhere"
    max_rate_dps = 1.0

    def connect(self) -> None: ...


def test_a_factory_that_breaks_the_protocol_is_refused_naming_what_is_missing():
    fake = registry.InstalledDriver("half_table", "tests:HALF", "tests", registry.Driver(
        "table", lambda section, clock, options: _Half(), SerialFields))
    drivers = {**registry.installed(), "half_table": fake}
    cfg = resolve_drivers(LabConfig.model_validate({**LAB, "table": {"driver": "half_table", "port": "/dev/null"}}),
                          {}, "lab", drivers)  # resolving is fine: the section is valid
    with pytest.raises(ConfigError, match=r"table: driver 'half_table' \(tests:HALF\) returned a _Half, which is not "
                                          r"a RateTable \(drivers.protocols\): missing close, identity, jog, status, "
                                          r"stop, velocity"):
        build_drivers(cfg, VirtualClock(), max_rate_dps=10)
    assert registry.protocol_members(RateTable) == ["address", "close", "connect", "identity", "jog", "max_rate_dps",
                                                    "name", "status", "stop", "velocity"]


# --- a lab's own driver package, installed into a temporary directory -----------------------------------


@pytest.fixture(scope="module")
def acme(tmp_path_factory):
    """tests/third_party_driver installed (a copy, so the build leaves nothing in the repository)."""
    work = tmp_path_factory.mktemp("acme")
    src = work / "src"
    shutil.copytree(ROOT / "tests" / "third_party_driver", src, ignore=shutil.ignore_patterns("build", "*.egg-info",
                                                                                            "__pycache__"))
    target = work / "site"
    # pip builds it in an isolated environment (setuptools from the package index, as tests/test_wheel.py's
    # build does): the venv's own setuptools may be too old to build a wheel without the `wheel` package.
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target),
                        str(src)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert (target / "acme_lab_drivers" / "__init__.py").exists()
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(target), env.get("PYTHONPATH", "")) if p)
    return env


def _cli(env, *args, stdin=None, timeout=180):
    return subprocess.run([sys.executable, "-m", "labrunner.cli", *map(str, args)], capture_output=True, text=True,
                          env=env, timeout=timeout, input=stdin)


def test_without_the_package_the_driver_is_unknown(tmp_path):
    lab = tmp_path / "lab.yaml"
    lab.write_text("chamber: {port: 1502}\ntable: {driver: acme_table, port: /dev/null}\nimu: {port: /dev/null}\n")
    r = _cli(dict(os.environ), "check", "--lab", lab)
    assert r.returncode == 2 and f"{lab}:2: table.driver: unknown table driver 'acme_table'" in r.stderr


def test_check_lists_the_third_party_drivers_and_names_the_broken_one(acme, tmp_path):
    lab = tmp_path / "lab.yaml"
    lab.write_text("chamber: {port: 1502}\ntable: {driver: acme_table, port: /dev/null, asset_tag: T-9}\n"
                   "imu: {port: /dev/null}\n")
    r = _cli(acme, "check", "--lab", lab)
    assert r.returncode == 0, r.stderr
    assert "table    driver acme_table (acme-lab-drivers) at /dev/null" in r.stdout
    assert ("acme_table (table: ACME rate table (labrunner language, asset-tagged); acme_lab_drivers:ACME_TABLE, "
            "from acme-lab-drivers)") in r.stdout
    assert "acme_missing (BROKEN: cannot be loaded: ModuleNotFoundError" in r.stdout
    assert "watlow_f4 (chamber:" in r.stdout  # the built-ins are still there
    lab.write_text("chamber: {port: 1502}\ntable: {driver: acme_table, port: /dev/null, asset_tag: ''}\n"
                   "imu: {port: /dev/null}\n")
    r = _cli(acme, "check", "--lab", lab)
    assert r.returncode == 2 and f"{lab}:2: table.asset_tag" in r.stderr, r.stderr
    lab.write_text("chamber: {port: 1502}\ntable: {driver: acme_missing, port: /dev/null}\nimu: {port: /dev/null}\n")
    r = _cli(acme, "check", "--lab", lab)
    assert r.returncode == 2 and "table driver 'acme_missing' (acme_lab_drivers.not_there:NOTHING, from " \
                                 "acme-lab-drivers) cannot be loaded: ModuleNotFoundError" in r.stderr, r.stderr


PROC = """\
name: acme rehearsal
temperatures: {list_c: [23]}
soak: {tolerance_c: 1.0, stable_window_s: 60, max_wait_s: 3600, sensor: chamber, poll_s: 10}
orientations: [{name: z_up, prompt: "Mount the IMU z up"}]
rates: {list_dps: [0, 20, -20]}
settle_s: 2
record_s: 10
record_poll_s: 5
fit: {run: false}
"""


def test_a_run_and_a_ping_use_the_third_party_driver(acme, tmp_path):
    lab_yaml = tmp_path / "served.yaml"
    served, _ = serve(lab_yaml, "--speed", "100", env=acme)
    try:
        import yaml

        lab = yaml.safe_load(lab_yaml.read_text())
        lab["table"] = {"driver": "acme_table", "asset_tag": "T-42", **lab["table"]}
        acme_lab = tmp_path / "acme.yaml"
        acme_lab.write_text(yaml.safe_dump(lab, sort_keys=False))

        r = _cli(acme, "check", "--lab", acme_lab, "--ping")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "table    ok: driver acme_table" in r.stdout
        assert "identity ACME RT-SIM-1 serial T-42 (driver acme_table, sent 1)" in r.stdout

        (tmp_path / "p.yaml").write_text(PROC)
        db = tmp_path / "acme.db"
        code, err = run_answering("run", tmp_path / "p.yaml", "--lab", acme_lab, "--db", db, "--quiet",
                                  timeout=120, env=acme)
        assert code == 0, err[-3000:]
        from labrunner.store import Store

        with Store.open_existing(db) as store:
            cid = store.resolve(None)
            steps = store.steps_frame(cid)
            info = store.campaign(cid)
        assert (steps.status == "done").all() and len(steps) == 3
        assert info.lab_config["table"]["driver"] == "acme_table"

        lab["table"]["driver"] = "acme_broken"
        del lab["table"]["asset_tag"]
        broken = tmp_path / "broken.yaml"
        broken.write_text(yaml.safe_dump(lab, sort_keys=False))
        r = _cli(acme, "run", tmp_path / "p.yaml", "--lab", broken, "--db", tmp_path / "b.db", "--quiet")
        assert r.returncode == 2, r.stderr
        assert "Traceback" not in r.stderr
        assert ("table: driver 'acme_broken' (acme_lab_drivers:ACME_BROKEN) returned a NotATable, which is not a "
                "RateTable (drivers.protocols): missing close, identity, jog, max_rate_dps, status, stop, velocity"
                ) in r.stderr
    finally:
        stop(served)
