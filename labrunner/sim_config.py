"""The one reader of sim configurations (seed, plants, IMU model, faults) for run, check and sim serve.

A sim configuration is kept as the mapping the user wrote (it is stored with a dry-run campaign,
and a resumed dry run rebuilds its simulated lab from it), validated here against the simulated
world and the fault-plan format, with errors naming the file and line.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labrunner.yaml_config import ConfigError, Range, check_ranges, did_you_mean, load_yaml, read_text

if TYPE_CHECKING:
    from labrunner.sims.world import SimLabConfig

log = logging.getLogger(__name__)

# Every number of a sim configuration, finite and physical: the simulated world integrates on
# `chamber.step_s` and the IMU streams at `imu_rate_hz`, so a tiny or infinite value would spin or
# hang a dry run; a fault at a negative time or beyond a few years would never fire.
DURATION_S = Range(0.0, 1e7, "s")
TAU_S = Range(1.0, 1e6, "s")
FAULT_RANGES = {"at_s": Range(0.0, 1e8, "s", nullable=True), "at_step": Range(0, 10**6, integer=True, nullable=True),
                "after_s": DURATION_S,
                "duration_s": DURATION_S, "count": Range(0, 10**6, integer=True)}
RANGES: dict[str, Range] = {
    "seed": Range(0, 2**32 - 1, integer=True),
    "imu_rate_hz": Range(0.1, 10000.0, "Hz"),
    "chamber.ambient_c": Range(-50.0, 60.0, "C"),
    "chamber.heat_rate_c_per_min": Range(0.01, 100.0, "C/min"),
    "chamber.cool_rate_c_per_min": Range(0.01, 100.0, "C/min"),
    "chamber.min_reachable_c": Range(-200.0, 100.0, "C"),
    "chamber.loss_tau_s": TAU_S,
    "chamber.kp_pct_per_c": Range(0.01, 10000.0, "%/C"),
    "chamber.ti_s": TAU_S,
    "chamber.fluctuation_c": Range(0.0, 10.0, "C"),
    "chamber.fluctuation_tau_s": TAU_S,
    "chamber.setpoint_min_c": Range(-200.0, 300.0, "C"),
    "chamber.setpoint_max_c": Range(-200.0, 300.0, "C"),
    "chamber.step_s": Range(0.05, 60.0, "s"),
    "chamber.controller_decimals": Range(0, 2, integer=True),  # the served F4's register 606
    "table.max_rate_dps": Range(0.01, 10000.0, "deg/s"),
    "table.accel_dps2": Range(0.01, 1e5, "deg/s^2"),
    "table.rate_accuracy": Range(0.0, 0.1),
    "table.encoder_resolution_dps": Range(1e-9, 1.0, "deg/s"),
    "imu_thermal.case_tau_s": TAU_S,
    "imu_thermal.self_heat_c": Range(0.0, 50.0, "C"),
    "imu_thermal.self_heat_tau_s": TAU_S,
    **{f"faults.{plan}[].{key}": r for plan in ("schedule", "random") for key, r in FAULT_RANGES.items()},
}


def sim_config_dict(source: str | Path | dict[str, Any] | None) -> dict[str, Any]:
    """Read (a path) or take (a mapping) a sim configuration and validate it; returns its mapping."""
    if source is None:
        return {}
    positions: dict[tuple[Any, ...], int] = {}
    if isinstance(source, dict):
        data, name = dict(source), "sim configuration"
    else:
        data, positions = load_yaml(read_text(source), str(source))
        name = str(source)
        if data is None:
            return {}
        if not isinstance(data, dict):
            raise ConfigError([f"{name}:1: a sim configuration must be a mapping"])
    problems = sim_config_problems(data, positions, name)
    if problems:
        raise ConfigError(problems)
    try:
        _build(data)
    except ConfigError as exc:  # the IMU model's file (the only file a sim configuration names)
        line = positions.get(("imu_model",), 1)
        raise ConfigError([f"{name}:{line}: imu_model: {m}" for m in exc.messages]) from None
    except RecursionError:
        raise ConfigError([f"{name}:{positions.get(('imu_model',), 1)}: imu_model: nested too deeply"]) from None
    except (ValueError, TypeError, KeyError, AttributeError, OverflowError, OSError) as exc:
        # What is left is the simulated world's own validation (the IMU model's effects, the operator,
        # the IMU format): located at the first key the message names.
        text = str(exc)
        named = [k for k in data if isinstance(k, str) and k in text]
        line = positions.get((min(named, key=text.index),), 1) if named else 1
        raise ConfigError([f"{name}:{line}: {text}"]) from None
    log.debug("sim configuration from %s: keys %s", name, sorted(data))
    return data


def sim_config_problems(data: dict[str, Any], positions: dict[tuple[Any, ...], int], name: str) -> list[str]:
    """Everything wrong with a sim configuration's keys, types and numbers, one located line each."""
    import dataclasses

    from labrunner.domain import ORIENTATIONS
    from labrunner.fault_plan import KINDS, Fault
    from labrunner.sims.lab import STARTING_FAULTS
    from labrunner.sims.world import SimLabConfig

    def at(*path: Any) -> str:
        for n in range(len(path), -1, -1):
            if path[:n] in positions:
                return f"{name}:{positions[path[:n]]}"
        return f"{name}:1"

    def keys(mapping: dict[Any, Any], known: Any, *path: Any) -> None:
        for key in mapping:
            if key not in known:
                where = ".".join(str(p) for p in (*path, key))
                problems.append(f"{at(*path, key)}: {where} is not a known key{did_you_mean(key, known)}; known: "
                                f"{', '.join(sorted(known))}")

    problems: list[str] = []
    config_fields = {f.name: f for f in dataclasses.fields(SimLabConfig)}
    keys(data, config_fields)
    for section in ("chamber", "table", "imu_thermal", "operator"):
        value = data.get(section)
        if value is None:
            continue
        if not isinstance(value, dict):
            problems.append(f"{at(section)}: {section} must be a mapping of keys to values")
            continue
        klass = config_fields[section].default_factory
        keys(value, {f.name for f in dataclasses.fields(klass)}, section)  # type: ignore[arg-type]
    operator = data.get("operator")
    if isinstance(operator, dict):  # the simulated operator's wrong mounts (SimOperatorParams checks them)
        from labrunner.sims.world import SimOperatorParams

        for key in ("wrong_mounts", "mounts_as"):
            if key in operator:
                try:
                    SimOperatorParams(**{key: operator[key]})
                except ValueError as exc:
                    problems.append(f"{at('operator', key)}: {exc}")
    orientation = data.get("orientation")
    if orientation is not None and orientation not in ORIENTATIONS:
        problems.append(f"{at('orientation')}: orientation must be one of {', '.join(ORIENTATIONS)}, got "
                        f"{orientation!r}")
    model = data.get("imu_model")
    if model is not None and not isinstance(model, (str, dict)):
        problems.append(f"{at('imu_model')}: imu_model must be a mapping or the path of a JSON/YAML model")
    chamber: dict[str, Any] = data["chamber"] if isinstance(data.get("chamber"), dict) else {}
    table = data["table"] if isinstance(data.get("table"), dict) else {}
    if "language" in table:
        from labrunner.drivers.table_profiles import LANGUAGES

        if table["language"] not in LANGUAGES:
            problems.append(f"{at('table', 'language')}: table.language must be one of {', '.join(LANGUAGES)}, got "
                            f"{table['language']!r}")
    if chamber.get("controller_units", "C") not in ("C", "F"):
        problems.append(f"{at('chamber', 'controller_units')}: chamber.controller_units must be C or F, got "
                        f"{chamber['controller_units']!r}")
    lo, hi = chamber.get("setpoint_min_c", -70.0), chamber.get("setpoint_max_c", 180.0)
    if isinstance(lo, (int, float)) and isinstance(hi, (int, float)) and not lo < hi:
        problems.append(f"{at('chamber', 'setpoint_min_c')}: chamber.setpoint_min_c must be below setpoint_max_c")
    faults = data.get("faults")
    if faults is not None and not isinstance(faults, dict):
        problems.append(f"{at('faults')}: faults must be a mapping (chamber, schedule, random)")
    elif faults:
        keys(faults, ("chamber", "schedule", "random"), "faults")
        start = faults.get("chamber")
        if start is not None and not isinstance(start, dict):
            problems.append(f"{at('faults', 'chamber')}: faults.chamber must be a mapping, e.g. "
                            "{compressor_failed: true}")
        elif start:
            keys(start, STARTING_FAULTS, "faults", "chamber")
            for key, value in start.items():
                if key in STARTING_FAULTS and not isinstance(value, bool):
                    problems.append(f"{at('faults', 'chamber', key)}: faults.chamber.{key} must be true or false, "
                                    f"got {value!r}")
        fault_keys = {f.name for f in dataclasses.fields(Fault)}
        for plan in ("schedule", "random"):
            items = faults.get(plan)
            if items is None:
                continue
            if not isinstance(items, list):
                problems.append(f"{at('faults', plan)}: faults.{plan} must be a list")
                continue
            for i, item in enumerate(items):
                where = f"faults.{plan}[{i}]"
                if not isinstance(item, dict):
                    problems.append(f"{at('faults', plan, i)}: {where} must be a mapping with kind, at_s or "
                                    "at_step, and duration_s or count")
                    continue
                keys(item, fault_keys, "faults", plan, i)
                if "kind" not in item:
                    problems.append(f"{at('faults', plan, i)}: {where}.kind is required")
                elif not isinstance(item["kind"], str) or item["kind"] not in KINDS:
                    problems.append(f"{at('faults', plan, i, 'kind')}: {where}.kind must be a fault kind, got "
                                    f"{item['kind']!r}{did_you_mean(item['kind'], KINDS)}; known: {', '.join(KINDS)}")
                if (item.get("at_s") is None) == (item.get("at_step") is None):
                    problems.append(f"{at('faults', plan, i)}: {where}: give at_s (campaign time) or at_step "
                                    "(a step index)")
                if problems:
                    continue
                try:
                    Fault(**item)
                except (ValueError, TypeError) as exc:
                    problems.append(f"{at('faults', plan, i)}: {where}: {exc}")
    problems += check_ranges(data, RANGES, positions, name)
    return sorted(problems, key=_line_of)


def _line_of(problem: str) -> int:
    """The line a located message names (`file:12: ...`), for reporting in file order."""
    head = problem.split(": ", 1)[0]
    line = head.rsplit(":", 1)[-1]
    return int(line) if line.isdigit() else 0


def _build(data: dict[str, Any]) -> None:
    from labrunner.sims.world import SimLabConfig

    config = SimLabConfig.from_dict(data)
    # The IMU model (inline or from a file) streams every frame: a NaN or infinite coefficient would
    # fill the data with NaN (its effects check their own parameters' ranges).
    where = _non_finite(config.imu_model.to_dict(), "imu_model")
    if where:
        raise ValueError(f"{where} must be a finite number")


def _non_finite(value: Any, path: str) -> str | None:
    """The path of the first NaN or infinite number in nested mappings and lists, or None."""
    if isinstance(value, float):
        return None if math.isfinite(value) else path
    if isinstance(value, dict):
        items: Any = value.items()
    elif isinstance(value, (list, tuple)):
        items = ((f"[{i}]", v) for i, v in enumerate(value))
    else:
        return None
    for key, item in items:
        found = _non_finite(item, f"{path}{key}" if str(key).startswith("[") else f"{path}.{key}")
        if found:
            return found
    return None


def load_sim_config(source: str | Path | dict[str, Any] | None) -> SimLabConfig:
    """The validated `SimLabConfig` of a sim configuration (path or mapping)."""
    from labrunner.sims.world import SimLabConfig

    return SimLabConfig.from_dict(sim_config_dict(source))


def has_fault_plan(sim_dict: dict[str, Any] | None) -> bool:
    """Whether a sim configuration schedules faults during the campaign (random or at given times)."""
    faults = (sim_dict or {}).get("faults") or {}
    return bool(faults.get("random") or faults.get("schedule"))
