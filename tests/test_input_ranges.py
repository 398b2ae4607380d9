"""Input that cannot hang or crash (issue 13, item 7): the range tables, the one YAML reader's limits, the
values a run used to ignore, and the warning of a simulator served beyond loopback."""

from __future__ import annotations

import io
import math
import re
import time
from argparse import Namespace
from contextlib import redirect_stderr
from pathlib import Path

import pytest
import yaml

from labrunner import lab as lab_module
from labrunner import procedure as procedure_module
from labrunner import sim_config as sim_config_module
from labrunner.commands.sim import is_loopback, serve_command
from labrunner.procedure import parse_procedure
from labrunner.sim_config import sim_config_dict
from labrunner.yaml_config import MAX_DOCUMENT_BYTES, ConfigError, Range, load_yaml, read_text

ROOT = Path(__file__).resolve().parents[1]
PROC = {"name": "t", "temperatures": {"list_c": [10, 30]}, "orientations": ["z_up"],
        "rates": {"list_dps": [0, 10]}, "soak": {"stable_window_s": 60, "max_wait_s": 600, "poll_s": 30},
        "record_s": 2, "record_poll_s": 1}


def _put(data: dict, dotted: str, value: object) -> dict:
    """`data` with `value` at a dotted path of a range table (`[]`: the first item of a list)."""
    node = data
    parts = dotted.split(".")
    for part in parts[:-1]:
        if part.endswith("[]"):
            node = node.setdefault(part[:-2], [{"at_s": 1.0, "kind": "imu_gap", "count": 1}])[0]
        else:
            node = node.setdefault(part, {})
    node[parts[-1]] = value
    return data


def _outside(r: Range) -> list[object]:
    """Values every range refuses: not finite, beyond each end, text, a boolean, a huge integer."""
    return [math.nan, math.inf, -math.inf, r.lo - max(1.0, abs(r.lo)), r.hi * 10 + 1, "1", True, 10**400]


def _procedure_with(dotted: str, value: object) -> dict:
    data = yaml.safe_load(yaml.safe_dump(PROC))
    if dotted.startswith("temperatures.") and dotted != "temperatures.list_c":
        data["temperatures"] = {"start_c": 10, "stop_c": 30, "step_c": 20}
    if dotted.startswith("rates.triangular"):
        data["rates"] = {"triangular": {"max_dps": 10, "step_dps": 5}}
    if dotted in ("temperatures.list_c", "rates.list_dps"):
        value = [value]
    return _put(data, dotted, value)


def test_the_base_procedure_is_valid():
    parse_procedure(yaml.safe_dump(PROC), "p.yaml")


@pytest.mark.parametrize("dotted", sorted(procedure_module.RANGES))
def test_every_procedure_number_is_ranged(dotted):
    r = procedure_module.RANGES[dotted]
    for value in _outside(r):
        text = yaml.safe_dump(_procedure_with(dotted, value)) if value != 10**400 else \
            yaml.safe_dump(_procedure_with(dotted, 7)).replace(" 7\n", " " + "9" * 60 + "\n")
        with pytest.raises(ConfigError) as info:
            parse_procedure(text, "p.yaml")
        message = str(info.value)
        key = re.escape(dotted) + (r"\[0\]" if dotted.endswith(("list_c", "list_dps")) else "")
        assert re.search(rf"p\.yaml:\d+: {key} must be", message), (value, message)
        assert r.describe() in message, message


@pytest.mark.parametrize("dotted", sorted(sim_config_module.RANGES))
def test_every_sim_number_is_ranged(dotted):
    r = sim_config_module.RANGES[dotted]
    for value in _outside(r)[:-1]:
        with pytest.raises(ConfigError) as info:
            sim_config_dict(_put({}, dotted, value))
        path = dotted.replace("[]", "[0]")
        assert f"{path} must be" in str(info.value) and r.describe() in str(info.value), str(info.value)


@pytest.mark.parametrize("dotted", sorted(lab_module.RANGES))
def test_every_lab_number_is_ranged(tmp_path, dotted):
    base = {"chamber": {"host": "127.0.0.1"}, "table": {"port": "socket://127.0.0.1:1"},
            "imu": {"port": "socket://127.0.0.1:2"}}
    r = lab_module.RANGES[dotted]
    for value in _outside(r)[:-1]:
        path = tmp_path / "lab.yaml"
        path.write_text(yaml.safe_dump(_put(yaml.safe_load(yaml.safe_dump(base)), dotted, value)))
        with pytest.raises(ConfigError) as info:
            lab_module.load_lab_config(path)
        assert re.search(rf"{re.escape(str(path))}:\d+: {re.escape(dotted)} must be", str(info.value)), str(info.value)


def test_range_messages_say_key_value_and_range():
    text = yaml.safe_dump(_procedure_with("soak.poll_s", 1e-9))
    with pytest.raises(ConfigError) as info:
        parse_procedure(text, "p.yaml")
    line = next(i for i, x in enumerate(text.splitlines(), 1) if re.match(r"\s+poll_s:", x))
    assert f"p.yaml:{line}: soak.poll_s must be in 0.1..3600 s, got 1e-09" in str(info.value)


def test_plan_sizes_are_limited_before_the_plan_is_expanded():
    data = _procedure_with("temperatures.step_c", 0.1)
    data["temperatures"].update(start_c=-100, stop_c=250)
    started = time.perf_counter()
    with pytest.raises(ConfigError, match="3,501 temperatures; at most 500"):
        parse_procedure(yaml.safe_dump(data), "p.yaml")
    data = yaml.safe_load(yaml.safe_dump(PROC))
    data["record_s"], data["soak"] = 86400, {"max_wait_s": 604800, "stable_window_s": 86400, "poll_s": 60}
    data["temperatures"] = {"start_c": -40, "stop_c": 84, "step_c": 1}
    with pytest.raises(ConfigError, match="days of lab time; at most 365"):
        parse_procedure(yaml.safe_dump(data), "p.yaml")
    assert time.perf_counter() - started < 5


def test_unused_procedure_keys_are_refused():
    for key in ("retries", "backoff_s"):
        with pytest.raises(ConfigError, match=rf"faults.{key} is not used: .*\(chamber.{key}, table.{key}\)"):
            parse_procedure(yaml.safe_dump({**PROC, "faults": {key: 2}}), "p.yaml")


def test_the_shipped_procedures_are_within_range():
    for name in procedure_module.shipped_procedures():
        procedure_module.load_procedure(name)


# --- the YAML reader ---------------------------------------------------------------------------------------


def test_duplicate_keys_name_the_second_line():
    with pytest.raises(ConfigError, match=r"x.yaml:4: duplicate key 'b' \(first at line 2\)"):
        load_yaml("a: 1\nb: 2\nc: {d: 1}\nb: 3\n", "x.yaml")
    with pytest.raises(ConfigError, match=r"x.yaml:4: duplicate key 'd' \(first at line 2\)"):
        load_yaml("c:\n  d: 1\n  e: 2\n  d: 1\n", "x.yaml")
    assert load_yaml("base: &b {x: 1}\nother:\n  <<: *b\n  y: 2\n", "x.yaml")[0]["other"] == {"x": 1, "y": 2}


def test_a_billion_laughs_is_refused_at_once():
    bomb = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8))
    started = time.perf_counter()
    with pytest.raises(ConfigError, match="expands to more than 100,000 values"):
        load_yaml(bomb, "x.yaml")
    assert time.perf_counter() - started < 1.0


def test_aliases_nesting_and_numbers_are_limited():
    with pytest.raises(ConfigError, match=r"x.yaml:2: more than 100 YAML aliases"):
        load_yaml("a: &a 1\nb: [" + ", ".join(["*a"] * 101) + "]\n", "x.yaml")
    assert len(load_yaml("a: &a 1\nb: [" + ", ".join(["*a"] * 100) + "]\n", "x.yaml")[0]["b"]) == 100
    with pytest.raises(ConfigError, match="recursive"):
        load_yaml("a: &a [1, *a]\n", "x.yaml")
    with pytest.raises(ConfigError, match="nested more than 40 levels"):
        load_yaml("a: " + "[" * 41 + "]" * 41, "x.yaml")
    with pytest.raises(ConfigError, match="nested too deeply|nested more than"):
        load_yaml("a: " + "[" * 5000 + "]" * 5000, "x.yaml")
    with pytest.raises(ConfigError, match="x.yaml:2: a number written with 65 characters"):
        load_yaml("a: 1\nb: " + "1" * 65 + "\n", "x.yaml")
    assert load_yaml("a: 1e-9\nb: 2E3\n", "x.yaml")[0] == {"a": 1e-9, "b": 2000.0}  # YAML 1.2 floats


def test_size_and_encoding_are_checked_when_read(tmp_path):
    big = tmp_path / "big.yaml"
    big.write_bytes(b"a: 1\n" + b"#" * (5 * MAX_DOCUMENT_BYTES))
    with pytest.raises(ConfigError, match=r"big.yaml: larger than 1,000,000 bytes"):
        read_text(big)
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(b"a: 1\nname: caf\xe9\n")
    with pytest.raises(ConfigError, match=r"latin.yaml:2: not UTF-8 text \(byte 0xe9 at offset 14\)"):
        read_text(latin)
    assert load_yaml(("\ufeff" + "a: 1\n"), "bom.yaml")[0] == {"a": 1}


def test_an_imu_model_file_goes_through_the_same_reader(tmp_path):
    model = tmp_path / "model.yaml"
    model.write_text("seed: 1\nseed: 2\n")
    with pytest.raises(ConfigError, match=r"model.yaml:2: duplicate key 'seed'"):
        sim_config_dict({"imu_model": str(model)})


def test_every_yaml_read_goes_through_yaml_config():
    """labrunner has one YAML reader: nothing else parses YAML (writing it is fine)."""
    readers = re.compile(r"yaml\.(safe_load|load|full_load|unsafe_load|compose|parse|scan)\b|yaml\.(Safe)?Loader\(")
    offenders = [f"{path.relative_to(ROOT)}:{n}" for folder in ("labrunner", "drivers", "sims")
                 for path in sorted((ROOT / folder).rglob("*.py")) if path.name != "yaml_config.py"
                 for n, line in enumerate(path.read_text().splitlines(), 1) if readers.search(line)]
    assert not offenders


# --- what run used to ignore ------------------------------------------------------------------------------


def test_a_dry_run_remount_takes_the_procedures_remount_s():
    from labrunner.lab import simulated_lab

    lab = simulated_lab(max_rate_dps=150, remount_s=42.0, orientation="z_up")
    try:
        before = lab.clock.now()
        lab.operator.remount("x_up", "turn it")
        assert lab.clock.now() - before == pytest.approx(42.0, abs=1.0)
    finally:
        lab.close()


def test_sim_config_keys_a_dry_run_ignores_are_refused_by_check_and_run(tmp_path):
    from labrunner.procedure import load_procedure
    from labrunner.run_validation import run_problems

    problems = run_problems(load_procedure("quick"), sim={"orientation": "x_up"})
    assert len(problems) == 1 and "orientation is not used by a dry run" in problems[0]


# --- sim serve beyond loopback --------------------------------------------------------------------------


def _serve(host: str) -> str:
    args = Namespace(config=None, speed=1.0, host=host, link="tcp", chamber_transport="tcp", profile="watlow_f4",
                     chamber_port=0, table_port=0, imu_port=0, lab_config=None, force=False, duration=0.05)
    err = io.StringIO()
    with redirect_stderr(err):
        assert serve_command(args) == 0
    return err.getvalue()


def test_serving_beyond_loopback_warns_in_one_line(capsys):
    warning = [line for line in _serve("0.0.0.0").splitlines() if "warning" in line]
    assert warning == [warning[0]] and "0.0.0.0, not loopback" in warning[0] and "reachable from the network" in \
        warning[0]
    assert "warning" not in _serve("127.0.0.1")
    capsys.readouterr()


def test_loopback_addresses():
    assert all(map(is_loopback, ["127.0.0.1", "127.3.2.1", "::1", "[::1]", "localhost"]))
    assert not any(map(is_loopback, ["0.0.0.0", "::", "192.168.1.50", "10.0.0.1", "no-such-host.invalid"]))


def _numeric_fields(model: type, prefix: str = "") -> list[str]:
    """Dotted paths of every number a pydantic schema takes (lists of numbers included)."""
    import typing

    from pydantic import BaseModel

    out = []
    for name, field in model.model_fields.items():
        path = f"{prefix}{name}"
        args = set(typing.get_args(field.annotation)) | {field.annotation}
        args |= {a for arg in list(args) for a in typing.get_args(arg)}
        sections = [a for a in args if isinstance(a, type) and issubclass(a, BaseModel)]
        if sections:
            out += _numeric_fields(sections[0], path + ".")
        elif args & {int, float} and bool not in args:
            out.append(path)
    return out


def test_the_range_tables_cover_every_number():
    """A number added to a schema without a range fails here (the tables are the one place for them)."""
    import dataclasses

    from labrunner.fault_plan import Fault
    from labrunner.procedure import ProcedureModel
    from labrunner.sims.world import SimLabConfig

    unused = {"faults.retries", "faults.backoff_s"}  # refused whenever written
    assert set(_numeric_fields(ProcedureModel)) - unused <= set(procedure_module.RANGES)
    sim_numbers = set()
    for f in dataclasses.fields(SimLabConfig):
        if f.type in ("int", "float"):
            sim_numbers.add(f.name)
        elif f.name in ("chamber", "table", "imu_thermal"):
            sim_numbers |= {f"{f.name}.{g.name}" for g in dataclasses.fields(f.default_factory())  # type: ignore[misc]
                            if g.type in ("int", "float")}
    sim_numbers |= {f"faults.{plan}[].{g.name}" for plan in ("schedule", "random") for g in dataclasses.fields(Fault)
                    if g.type != "str"}
    assert sim_numbers <= set(sim_config_module.RANGES), sim_numbers - set(sim_config_module.RANGES)


def test_resume_on_a_lab_given_anew_is_checked_as_run_checks_it(tmp_path):
    """A real-lab campaign resumed with another lab configuration: what run refuses at its start, resume
    refuses before building an instrument, and leaves the campaign resumable (its lease released)."""
    from labrunner.campaign_session import start_resume, start_run

    proc, lab, other = tmp_path / "p.yaml", tmp_path / "lab.yaml", tmp_path / "lab100.yaml"
    proc.write_text(yaml.safe_dump(PROC))
    text = ("chamber: {host: 127.0.0.1, port: 9}\ntable: {port: 'socket://127.0.0.1:9'}\n"
            "imu: {port: 'socket://127.0.0.1:9', rate_hz: 50}\n")
    lab.write_text(text)
    other.write_text(text.replace("rate_hz: 50", "rate_hz: 100"))
    db = tmp_path / "c.db"
    start_run(proc, db=db, lab=lab, fit_out=tmp_path / "fit").close()  # created, never run
    with pytest.raises(ConfigError, match=rf"sample_rate_hz 50 Hz is not the IMU's rate \({re.escape(str(other))}"):
        start_resume(db, lab=other)
    start_resume(db, lab=lab).close()


@pytest.mark.parametrize("name, content, expect", [
    ("missing.json", None, r"sim.yaml:2: imu_model: .*missing.json: file not found"),
    ("deep.json", "[" * 100_000, r"sim.yaml:2: imu_model: nested too deeply"),
    ("nan.json", '{"accel": {"noise_density": NaN}}', r"sim.yaml:2: imu_model.accel.noise_density must be a finite"),
    ("big.json", "[" + "0," * 600_000 + "0]", r"sim.yaml:2: imu_model: .*big.json: larger than 1,000,000 bytes"),
    ("bomb.yaml", "a: &a [x, x]\n" + "".join(f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}, "
                                             f"*{chr(97 + i)}, *{chr(97 + i)}]\n" for i in range(12)),
     r"sim.yaml:2: imu_model: .*bomb.yaml:\d+: the document expands"),
])
def test_an_imu_model_file_is_read_with_the_same_limits(tmp_path, name, content, expect):
    model = tmp_path / name
    if content is not None:
        model.write_text(content)
    sim = tmp_path / "sim.yaml"
    sim.write_text(f"seed: 1\nimu_model: {model}\n")
    with pytest.raises(ConfigError, match=expect):
        sim_config_dict(sim)
