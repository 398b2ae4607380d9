"""Fuzz of procedures, sim configurations and lab configurations through the command line's entry points
(issue 13, item 7): `labrunner check` never prints a traceback, never takes 10 s, and `labrunner run --sim`
starts exactly what `check` accepts. A run that check refuses is refused before any simulated instrument is
built (no store file is written); a run that check accepts starts, passes the sequencer's preflight (the
instruments answer and accept the procedure's temperatures and rates) and is stopped by the test where the
first remount would begin (the `mounting` state's handler is replaced by a pause), so no campaign is run.
With a fault plan, a fault may legitimately strike during preflight: there the run need only start.

The hostile cases are listed explicitly (`HOSTILE`, more than 40); hypothesis then draws procedures and
configurations with hostile or in-range values at every key of the range tables.
"""

from __future__ import annotations

import io
import math
import os
import re
import time
from contextlib import redirect_stderr, redirect_stdout
from datetime import timedelta
from pathlib import Path
from typing import Any
from unittest import mock

import pytest
import yaml
from hypothesis import HealthCheck, currently_in_test_context, event, given, settings
from hypothesis import strategies as st

import labrunner.sequencer as sequencer
import labrunner.sims.lab as sims_lab
from labrunner import lab as lab_module
from labrunner import procedure as procedure_module
from labrunner import sim_config as sim_config_module
from labrunner.cli import main

CHECK_LIMIT_S = 10.0
PROC = """name: fuzz
temperatures: {list_c: [10, 30]}
soak: {tolerance_c: 0.5, stable_window_s: 60, max_wait_s: 600, poll_s: 30}
orientations: [z_up]
rates: {list_dps: [0, 10]}
settle_s: 1
record_s: 2
record_poll_s: 1
sample_rate_hz: 50
"""
LAB = """name: lab
chamber: {transport: tcp, host: 127.0.0.1, port: 5020, profile: watlow_f4}
table: {port: socket://127.0.0.1:5021}
imu: {port: socket://127.0.0.1:5022, rate_hz: 50}
"""
BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [{', '.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8))


def _cli(args: list[Any]) -> tuple[int, str, str, float]:
    out, err = io.StringIO(), io.StringIO()
    started = time.perf_counter()
    with redirect_stdout(out), redirect_stderr(err):
        code = main([str(a) for a in args])
    return code, out.getvalue(), err.getvalue(), time.perf_counter() - started


def _check(args: list[Any]) -> tuple[int, str]:
    code, out, err, took = _cli(["check", *args])
    assert took < CHECK_LIMIT_S, f"check took {took:.1f} s"
    assert "Traceback" not in err + out
    assert code in (0, 2), (code, err)
    return code, err


def _run_start(proc: Path, sim: Path | None, db: Path) -> tuple[int, str, int, int, int]:
    """`labrunner run PROC --sim [--sim-config SIM]`, paused where the first remount would begin; returns the
    exit code, stderr, how many runs reached the sequencer, how many got through its preflight, and how many
    simulated labs were built."""
    started: list[int] = []
    through_preflight: list[int] = []
    built: list[int] = []
    real_init = sims_lab.SimLab.__init__
    real_run = sequencer.CampaignRunner.run

    def counting_init(self: Any, *a: Any, **k: Any) -> None:
        built.append(1)
        real_init(self, *a, **k)

    def counting_run(runner: Any) -> str:
        started.append(runner.cid)
        return real_run(runner)

    def pause_at_mounting(runner: Any) -> None:
        through_preflight.append(runner.cid)
        runner.pause()

    with mock.patch.object(sequencer.CampaignRunner, "run", counting_run), \
            mock.patch.object(sequencer.CampaignRunner, "_do_mounting", pause_at_mounting), \
            mock.patch.object(sims_lab.SimLab, "__init__", counting_init):
        code, out, err, _ = _cli(["run", proc, "--sim", "--db", db, "--quiet", "--no-auto-resume"]
                                 + (["--sim-config", sim] if sim is not None else []))
    assert "Traceback" not in err + out
    return code, err, len(started), len(through_preflight), len(built)


def _located(err: str, paths: list[Path]) -> bool:
    """The message names one of the files (and, where it can, a line)."""
    return any(str(p) in err for p in paths)


def assert_run_starts_iff_check_accepts(d: Path, proc_text: str | bytes, sim_text: str | bytes | None = None,
                                        expect: str | None = None) -> None:
    proc = d / "proc.yaml"
    (proc.write_bytes if isinstance(proc_text, bytes) else proc.write_text)(proc_text)  # type: ignore[operator]
    sim = None
    if sim_text is not None:
        sim = d / "sim.yaml"
        (sim.write_bytes if isinstance(sim_text, bytes) else sim.write_text)(sim_text)  # type: ignore[operator]
    code, err = _check([proc, "--sim"] + (["--sim-config", sim] if sim is not None else []))
    files = [proc] + ([sim] if sim is not None else [])
    if code:
        assert _located(err, files), err
    if expect is not None:
        if expect == "ok":
            assert code == 0, err
        else:
            assert code == 2 and re.search(expect, err), err
    if currently_in_test_context():
        event("check accepted: the run starts" if code == 0 else "check refused: so does run")
    db = d / "run.db"
    run_code, run_err, started, through_preflight, built = _run_start(proc, sim, db)
    if code == 0:
        assert started == 1 and run_code == 3, f"check accepted it, run did not start: {run_err}"
        faulty = sim is not None and bool((yaml.safe_load(sim.read_text()) or {}).get("faults"))
        assert through_preflight == 1 or faulty, f"check accepted it, preflight refused it: {run_err}"
    else:
        assert run_code == 2 and started == 0 and built == 0, f"check refused it, run did not: {run_err}"
        assert not db.exists()
        assert _located(run_err, files), run_err


def _with(text: str, line: str) -> str:
    return text + line + "\n"


def _replace(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new)


# (id, procedure text, sim configuration text or None, what check must say: a regex, or "ok")
HOSTILE: list[tuple[str, str | bytes, str | bytes | None, str]] = [
    ("settle_inf", _replace(PROC, "settle_s: 1", "settle_s: .inf"), None, r"proc.yaml:6: settle_s must be a finite"),
    ("record_inf", _replace(PROC, "record_s: 2", "record_s: .inf"), None, r":7: record_s must be a finite"),
    ("record_1e308", _replace(PROC, "record_s: 2", "record_s: 1e308"), None, r":7: record_s must be in 0.01\.\.86400"),
    ("record_nan", _replace(PROC, "record_s: 2", "record_s: .nan"), None, r"record_s must be a finite number"),
    ("record_negative", _replace(PROC, "record_s: 2", "record_s: -1"), None, r"record_s must be in .*got -1"),
    ("record_true", _replace(PROC, "record_s: 2", "record_s: true"), None, r"record_s must be a number .*got true"),
    ("record_string", _replace(PROC, "record_s: 2", "record_s: '2'"), None, r"record_s must be a number .*got '2'"),
    ("record_list", _replace(PROC, "record_s: 2", "record_s: [2]"), None, r"record_s must be a number"),
    ("record_null", _replace(PROC, "record_s: 2", "record_s: null"), None, r":7: record_s"),
    ("record_huge_int", _replace(PROC, "record_s: 2", "record_s: 1" + "0" * 5000), None, r":7: a number written"),
    ("record_big_int", _replace(PROC, "record_s: 2", "record_s: " + "9" * 40), None, r"an integer of \d+ bits"),
    ("step_tiny", _replace(PROC, "{list_c: [10, 30]}", "{start_c: 10, stop_c: 30, step_c: 1e-9}"), None,
     r":2: temperatures.step_c must be in 0.1\.\.200 C, got 1e-09"),
    ("poll_tiny", _replace(PROC, "poll_s: 30}", "poll_s: 1e-7}"), None, r":3: soak.poll_s must be in 0.1"),
    ("soak_huge", _replace(PROC, "max_wait_s: 600", "max_wait_s: 1e12"), None, r"soak.max_wait_s must be in"),
    ("window_zero", _replace(PROC, "stable_window_s: 60", "stable_window_s: 0"), None, r"soak.stable_window_s"),
    ("sample_rate_huge", _replace(PROC, "sample_rate_hz: 50", "sample_rate_hz: 1e9"), None, r":9: sample_rate_hz"),
    ("rate_inf", _replace(PROC, "[0, 10]", "[0, .inf]"), None, r":5: rates.list_dps\[1\] must be a finite"),
    ("triangular_tiny", _replace(PROC, "{list_dps: [0, 10]}", "{triangular: {max_dps: 100, step_dps: 1e-6}}"),
     None, r"rates.triangular.step_dps must be in"),
    ("triangular_repeats", _replace(PROC, "{list_dps: [0, 10]}", "{triangular: {max_dps: 10000, step_dps: 0.01}}"),
     None, r"rate steps; at most"),
    ("temperatures_repeats", _replace(PROC, "{list_c: [10, 30]}", "{start_c: -100, stop_c: 250, step_c: 0.1}"),
     None, r"temperatures; at most"),
    ("temperature_nan", _replace(PROC, "[10, 30]", "[10, .nan]"), None, r":2: temperatures.list_c\[1\] must be a fin"),
    ("temperature_huge", _replace(PROC, "[10, 30]", "[10, 1e6]"), None, r"temperatures.list_c\[1\] must be in -100"),
    ("rate_huge_negative", _replace(PROC, "[0, 10]", "[0, -1e12]"), None, r"rates.list_dps\[1\] must be in"),
    ("sample_rate_tiny", _replace(PROC, "sample_rate_hz: 50", "sample_rate_hz: 1e-9"), None, r"sample_rate_hz must"),
    ("count_negative", _with(PROC, "faults: {max_dropped_frames: -1}"), None, r"faults.max_dropped_frames must"),
    ("imu_rating_below_plan", _with(PROC, "safety: {imu_max_temp_c: 0}"), None, r"IMU interlock would trip"),
    ("safety_inf", _with(PROC, "safety: {chamber_max_c: .inf}"), None, r":10: safety.chamber_max_c must be a finite"),
    ("safety_minus_inf", _with(PROC, "safety: {chamber_min_c: -.inf}"), None, r"safety.chamber_min_c"),
    ("remount_negative", _with(PROC, "remount_s: -5"), None, r":10: remount_s must be in 0\.\.86400 s, got -5"),
    ("rerecords_billion", _with(PROC, "faults: {max_rerecords: 1000000000}"), None, r"faults.max_rerecords"),
    ("retries_unused", _with(PROC, "faults: {retries: 3}"), None, r"faults.retries is not used"),
    ("order_fraction", _with(PROC, "fit: {polynomial_order: 2.5}"), None, r"fit.polynomial_order must be a whole"),
    ("average_tiny", _with(PROC, "monitor: {average_s: 1e-9}"), None, r"monitor.average_s"),
    ("record_poll_tiny", _replace(PROC, "record_poll_s: 1", "record_poll_s: 1e-9"), None, r"record_poll_s"),
    ("mount_tries_nan", _with(PROC, "mount_check: {tries: .nan}"), None, r"mount_check.tries"),
    ("duplicate_key", _with(PROC, "record_s: 3"), None, r":10: duplicate key 'record_s' \(first at line 7\)"),
    ("alias_bomb", _with(PROC, BOMB), None, r"expands to more than"),
    ("alias_count", _with(PROC, "x: &x 1\ny: [" + ", ".join(["*x"] * 150) + "]"), None, r"more than 100 YAML alias"),
    ("alias_recursive", _with(PROC, "x: &x [*x]"), None, r"recursive"),
    ("five_megabytes", PROC + "# " + "x" * (5 * 1024 * 1024) + "\n", None, r"larger than 1,000,000 bytes"),
    ("empty_file", "", None, r"proc.yaml:1: expected a mapping .* empty"),
    ("binary_garbage", bytes(range(256)) * 4, None, r"proc.yaml:\d+: not (valid YAML|UTF-8)"),
    ("nul_bytes", PROC.encode() + b"\x00\x01\x02\n", None, r"proc.yaml:10: not valid YAML: character U\+0000"),
    ("non_utf8", PROC.replace("fuzz", "f\xfczz").encode("latin-1"), None, r"proc.yaml:1: not UTF-8 text"),
    ("unknown_key", _with(PROC, "recrod_s: 3"), None, r":10: recrod_s is not a known key \(did you mean 'record_s'"),
    ("unknown_nested_key", _replace(PROC, "poll_s: 30}", "pol_s: 30}"), None, r"soak.pol_s .*did you mean 'poll_s'"),
    ("missing_rates", "\n".join(x for x in PROC.splitlines() if not x.startswith("rates")) + "\n", None,
     r"rates is required"),
    ("deep_nesting", _with(PROC, "deep: " + "[" * 200 + "]" * 200), None, r"nested"),
    ("tabs", _replace(PROC, "settle_s: 1", "settle_s:\n\t1"), None, r"not valid YAML"),
    ("bom_is_fine", "\ufeff" + PROC, None, "ok"),
    ("list_for_mapping", _replace(PROC, "{list_c: [10, 30]}", "[10, 30]"), None, r"temperatures must be a mapping"),
    ("mapping_for_list", _replace(PROC, "[z_up]", "{z_up: 1}"), None, r"orientations must be a list"),
    ("top_level_list", "- 1\n- 2\n", None, r"expected a mapping"),
    ("python_tag", "!!python/object/apply:os.system ['true']\n", None, r"not valid YAML"),
    ("two_documents", PROC + "---\nname: other\n", None, r"not valid YAML"),
    ("valid", PROC, None, "ok"),
    # sim configurations, with the valid procedure
    ("sim_seed_negative", PROC, "seed: -1\n", r"sim.yaml:1: seed must be in 0\.\.4294967295"),
    ("sim_step_tiny", PROC, "chamber: {step_s: 1e-9}\n", r"sim.yaml:1: chamber.step_s must be in"),
    ("sim_imu_rate_inf", PROC, "imu_rate_hz: .inf\n", r"imu_rate_hz must be a finite"),
    ("sim_fault_negative", PROC, "faults:\n  schedule:\n    - {at_s: -5, kind: imu_gap, count: 2}\n",
     r"sim.yaml:3: faults.schedule\[0\].at_s must be in 0"),
    ("sim_fault_inf", PROC, "faults:\n  schedule:\n    - {at_s: 5, kind: modbus_outage, duration_s: .inf}\n",
     r"duration_s must be a finite"),
    ("sim_fault_kind", PROC, "faults:\n  schedule:\n    - {at_s: 5, kind: imu_gapp, count: 2}\n",
     r"did you mean 'imu_gap'"),
    ("sim_unknown_key", PROC, "sed: 3\n", r"sim.yaml:1: sed is not a known key \(did you mean 'seed'"),
    ("sim_faults_typo", PROC, "faults: {shedule: []}\n", r"faults.shedule is not a known key"),
    ("sim_starting_fault_text", PROC, "faults: {chamber: {heater_failed: 'yes'}}\n", r"must be true or false"),
    ("sim_plant_text", PROC, "chamber: {ambient_c: warm}\n", r"chamber.ambient_c must be a number"),
    ("sim_imu_rate_mismatch", PROC, "imu_rate_hz: 100\n", r"proc.yaml:9: sample_rate_hz 50 Hz is not the simulated"),
    ("sim_table_too_slow", PROC, "table: {max_rate_dps: 5}\n", r"proc.yaml:5: rates 10 deg/s exceed the simulated"),
    ("sim_setpoint_range", PROC, "chamber: {setpoint_max_c: 20}\n", r"proc.yaml:2: temperatures 30 C is outside"),
    ("sim_fault_beyond_plan", PROC, "faults:\n  schedule:\n    - {at_step: 99, kind: imu_gap, count: 2}\n",
     r"beyond the procedure's last step"),
    ("sim_orientation_ignored", PROC, "orientation: x_up\n", r"orientation is not used by a dry run"),
    ("sim_imu_model_number", PROC, "imu_model: 42\n", r"imu_model must be a mapping"),
    ("sim_imu_model_nan", PROC, "seed: 1\nimu_model: {accel: {noise_density: .nan}}\n",
     r"sim.yaml:2: imu_model.accel.noise_density must be a finite number"),
    ("sim_imu_model_shape", PROC, "imu_model: {accel: {bias: [1]}}\n", r"sim.yaml:1: cannot reshape"),
    ("sim_duplicate_key", PROC, "seed: 1\nseed: 2\n", r"sim.yaml:2: duplicate key 'seed'"),
    ("sim_bomb", PROC, BOMB, r"sim.yaml:\d+: the document expands"),
    ("sim_list", PROC, "- 1\n", r"sim.yaml:1: a sim configuration must be a mapping"),
    ("sim_valid", PROC, "seed: 4\nfaults:\n  schedule:\n    - {at_step: 1, kind: imu_gap, count: 2}\n", "ok"),
]


def test_there_are_forty_hostile_cases():
    assert len([c for c in HOSTILE if c[3] != "ok"]) >= 40


@pytest.mark.parametrize("proc_text, sim_text, expect", [c[1:] for c in HOSTILE], ids=[c[0] for c in HOSTILE])
def test_hostile_procedures_and_sim_configurations(tmp_path, proc_text, sim_text, expect):
    assert_run_starts_iff_check_accepts(tmp_path, proc_text, sim_text, expect)


HOSTILE_LABS = [
    ("rtu_without_serial_port", _replace(LAB, "transport: tcp, host: 127.0.0.1, port: 5020", "transport: rtu"),
     r"lab.yaml:2: .*rtu needs serial_port"),
    ("register_text", _replace(LAB, "profile: watlow_f4", "profile: {base: watlow_f4, name: x, process_value: abc}"),
     r"lab.yaml:2: chamber.profile.process_value must be"),
    ("register_negative", _replace(LAB, "profile: watlow_f4", "profile: {base: watlow_f4, name: x, process_value: -5}"),
     r"process_value must be in 0\.\.65535, got -5"),
    ("fixed_range_one", _replace(LAB, "profile: watlow_f4", "profile: {base: watlow_f4, name: x, fixed_range_c: [1]}"),
     r"fixed_range_c must be \[low, high\]"),
    ("timeout_tiny", _replace(LAB, "port: 5020,", "port: 5020, timeout_s: 1e-9,"), r"chamber.timeout_s must be in"),
    ("speed_inf", _with(LAB, "clock: {speed: .inf}"), r"lab.yaml:5: clock.speed must be a finite"),
    ("retries_billion", _replace(LAB, "5021}", "5021, retries: 1000000000}"), r"table.retries must be in 0\.\.20"),
    ("unknown_key", _replace(LAB, "rate_hz: 50}", "rate_hz: 50, baudrat: 9600}"), r"did you mean 'baudrate'"),
    ("port_text", _replace(LAB, "port: 5020", "port: abc"), r"lab.yaml:2: chamber.port must be"),
    ("imu_rate_zero", _replace(LAB, "rate_hz: 50", "rate_hz: 0"), r"imu.rate_hz must be in 0.1"),
    ("duplicate_section", _with(LAB, "imu: {port: /dev/null}"), r"lab.yaml:5: duplicate key 'imu'"),
]


@pytest.mark.parametrize("lab_text, expect", [c[1:] for c in HOSTILE_LABS], ids=[c[0] for c in HOSTILE_LABS])
def test_hostile_lab_configurations(tmp_path, lab_text, expect):
    lab = tmp_path / "lab.yaml"
    lab.write_text(lab_text)
    code, err = _check(["--lab", lab])
    assert code == 2 and re.search(expect, err), err
    proc = tmp_path / "proc.yaml"
    proc.write_text(PROC)
    assert _check([proc, "--lab", lab])[0] == 2


def test_procedure_against_a_lab_configuration(tmp_path):
    """What run refuses at the start on a real lab is refused by check with the lab: the IMU's rate."""
    lab, proc = tmp_path / "lab.yaml", tmp_path / "proc.yaml"
    lab.write_text(_replace(LAB, "rate_hz: 50", "rate_hz: 100"))
    proc.write_text(PROC)
    code, err = _check([proc, "--lab", lab])
    assert code == 2 and f"{proc}:9: sample_rate_hz 50 Hz is not the IMU's rate ({lab}: imu.rate_hz 100 Hz)" in err
    code, out, err, _ = _cli(["run", proc, "--lab", lab, "--db", tmp_path / "x.db"])
    assert code == 2 and "sample_rate_hz 50 Hz is not the IMU's rate" in err and not (tmp_path / "x.db").exists()


# --- generated cases ---------------------------------------------------------------------------------------

HOSTILE_VALUES = [math.nan, math.inf, -math.inf, -1, 0, 1e-9, 1e-7, 1e12, 1e308, 10**30, True, False, "60", "abc",
                  None, [1], {"a": 1}, ""]


def _value_for(r: Any) -> st.SearchStrategy[Any]:
    """A hostile value, or one inside the range (so some generated files are valid and start a run)."""
    inside = st.integers(int(r.lo), int(min(r.hi, r.lo + 1000))) if r.integer else st.floats(r.lo, r.hi)
    hostile = st.one_of(st.sampled_from(HOSTILE_VALUES), st.floats(), st.integers(-10**12, 10**12))
    return st.one_of(inside, hostile)  # half inside: edits that pass, and edits that together do not


def _set(data: dict[str, Any], dotted: str, value: Any) -> None:
    """Put `value` at a dotted path of the range tables (`faults.schedule[].at_s`: in a first list item)."""
    parts = dotted.split(".")
    node: Any = data
    for part in parts[:-1]:
        if part.endswith("[]"):
            items = node.setdefault(part[:-2], [{"at_s": 10.0, "kind": "imu_gap", "count": 1}])
            node = items[0] if isinstance(items, list) and items and isinstance(items[0], dict) else {}
        else:
            child = node.get(part)
            node = node.setdefault(part, {}) if child is None or not isinstance(child, dict) else child
    key = parts[-1]
    node[key] = value if not (key in ("list_c", "list_dps") and not isinstance(value, list)) else [value]


def _procedure_with(edits: list[tuple[str, Any]]) -> dict[str, Any]:
    data = yaml.safe_load(PROC)
    for dotted, value in edits:
        if dotted.startswith("temperatures.") and dotted != "temperatures.list_c":
            data["temperatures"] = {"start_c": 10, "stop_c": 30, "step_c": 20}
        if dotted.startswith("rates.triangular"):
            data["rates"] = {"triangular": {"max_dps": 10, "step_dps": 5}}
        _set(data, dotted, value)
    return data


def _edits(table: dict[str, Any]) -> st.SearchStrategy[list[tuple[str, Any]]]:
    keys = sorted(table)
    return st.lists(st.sampled_from(keys).flatmap(lambda k: st.tuples(st.just(k), _value_for(table[k]))),
                    max_size=3)


# Derandomized in the suite (CI sees the same cases every time); LABRUNNER_FUZZ_EXAMPLES=5000
# LABRUNNER_FUZZ_RANDOM=1 hunts further.
FUZZ = settings(max_examples=int(os.environ.get("LABRUNNER_FUZZ_EXAMPLES", "100")),
                # An example is a check (held to CHECK_LIMIT_S itself) and a run's start and preflight.
                deadline=timedelta(seconds=3 * CHECK_LIMIT_S), derandomize=not os.environ.get("LABRUNNER_FUZZ_RANDOM"),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


@FUZZ
@given(proc_edits=_edits(procedure_module.RANGES), sim_edits=_edits(sim_config_module.RANGES),
       extra=st.sampled_from([None, None, None, ("recrod_s", 3), ("soak.pol_s", 1)]), with_sim=st.booleans())
def test_generated_procedures_and_sim_configurations(tmp_path_factory, proc_edits, sim_edits, extra, with_sim):
    proc = _procedure_with(proc_edits + ([extra] if extra else []))
    sim: dict[str, Any] = {}
    for dotted, value in sim_edits:
        _set(sim, dotted, value)
    d = tmp_path_factory.mktemp("fuzz")
    assert_run_starts_iff_check_accepts(d, yaml.safe_dump(proc), yaml.safe_dump(sim) if with_sim else None)


@settings(FUZZ, max_examples=max(1, FUZZ.max_examples // 2))
@given(edits=_edits(dict(lab_module.RANGES)))
def test_generated_lab_configurations(tmp_path_factory, edits):
    data = yaml.safe_load(LAB)
    for dotted, value in edits:
        _set(data, dotted, value)
    d = tmp_path_factory.mktemp("lab")
    lab = d / "lab.yaml"
    lab.write_text(yaml.safe_dump(data))
    code, err = _check(["--lab", lab])
    if code:
        assert str(lab) in err and re.search(rf"{re.escape(str(lab))}:\d+: ", err), err
    proc = d / "proc.yaml"
    proc.write_text(PROC)
    combined, err = _check([proc, "--lab", lab])
    if code:
        assert combined == 2  # a lab configuration check refuses is refused with any procedure
    elif combined:
        assert "is not the IMU's rate" in err, err  # the only thing a procedure adds against a valid lab
    # `run --lab`: refused before a driver is built, or started (and stopped before it connects to anything).
    run_code, run_err, started, drivers_built = _run_lab_start(proc, lab, d / "run.db")
    if combined:
        assert run_code == 2 and started == 0 and drivers_built == 0, run_err
        assert not (d / "run.db").exists()
    else:
        assert run_code == 3 and started == 1, f"check accepted it, run did not start: {run_err}"


def _run_lab_start(proc: Path, lab: Path, db: Path) -> tuple[int, str, int, int]:
    """`labrunner run PROC --lab LAB`, stopped where the sequencer would begin (before preflight connects to
    the instruments, which are not there); returns the exit code, stderr, runs started and drivers built."""
    started: list[int] = []
    built: list[int] = []
    real_build = lab_module.build_drivers

    def counting_build(*a: Any, **k: Any) -> Any:
        built.append(1)
        return real_build(*a, **k)

    def stop_at_start(runner: Any) -> str:
        started.append(runner.cid)
        return "paused"

    with mock.patch.object(sequencer.CampaignRunner, "run", stop_at_start), \
            mock.patch.object(lab_module, "build_drivers", counting_build):
        code, out, err, _ = _cli(["run", proc, "--lab", lab, "--db", db, "--quiet"])
    assert "Traceback" not in err + out
    return code, err, len(started), len(built)
