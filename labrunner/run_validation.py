"""What a run refuses at its start, checked before any instrument is built or touched.

`labrunner run` (through `campaign_session.start_run`) and `labrunner check` both call
`validate_run`, so `check` accepts nothing that `run` would refuse at its start. It checks a
procedure against what it will run on, as far as that is known without talking to an
instrument: the IMU's frame rate (a record waits for `record_s x sample_rate_hz` frames),
and for a dry run the simulated controller's setpoint range and the simulated table's maximum
rate (what preflight would refuse), the fault plan's steps (a fault at a step the plan does not
have never fires) and the keys a dry run would ignore. A real controller's setpoint range and a
real table's limits are read at preflight (or by `labrunner check --ping`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labrunner.sim_config import sim_config_problems
from labrunner.yaml_config import ConfigError, load_yaml, read_text

if TYPE_CHECKING:
    from labrunner.lab import LabConfig
    from labrunner.procedure import Procedure

log = logging.getLogger(__name__)

Positions = Mapping[tuple[Any, ...], int]


def _positions(text: str | None, source: str) -> Positions:
    if text is None:
        return {}
    try:
        return load_yaml(text, source)[1]
    except ConfigError:  # it was read once already; positions are only for the messages
        return {}


def _at(source: str, positions: Positions, *path: Any) -> str:
    for n in range(len(path), -1, -1):
        if path[:n] in positions:
            return f"{source}:{positions[path[:n]]}"
    return source


def _file_positions(path: str | Path | None) -> Positions:
    if path is None:
        return {}
    try:
        return _positions(read_text(path), str(path))
    except ConfigError:
        return {}


def validate_run(procedure: Procedure, *, lab: LabConfig | None = None, sim: dict[str, Any] | None = None,
                 lab_source: str | Path | None = None, sim_source: str | Path | None = None) -> None:
    """Refuse (ConfigError, one located line per problem) a procedure that its lab (`lab`, a real
    one) or its simulated lab (`sim`, a sim configuration's mapping; {} for the default) would
    refuse at the start of a run. Talks to nothing."""
    problems = run_problems(procedure, lab=lab, sim=sim, lab_source=lab_source, sim_source=sim_source)
    if problems:
        raise ConfigError(problems)


def run_problems(procedure: Procedure, *, lab: LabConfig | None = None, sim: dict[str, Any] | None = None,
                 lab_source: str | Path | None = None, sim_source: str | Path | None = None) -> list[str]:
    """What `validate_run` refuses, one located line each (empty: the run may start)."""
    pos = _positions(procedure.text, procedure.source)

    def at(*path: Any) -> str:
        return _at(procedure.source, pos, *path)

    problems: list[str] = []
    if sim is not None:
        name = str(sim_source) if sim_source is not None else "sim configuration"
        sim_pos = _file_positions(sim_source)
        problems += sim_config_problems(sim, dict(sim_pos), name)  # --seed and --faults join the mapping
        if problems:
            return problems
        problems += _sim_problems(procedure, sim, name, sim_pos, at)
    if lab is not None:
        name = str(lab_source) if lab_source is not None else f"lab configuration '{lab.name}'"
        problems += _lab_problems(procedure, lab, name, _file_positions(lab_source), at)
    return problems


def _sim_problems(procedure: Procedure, sim: dict[str, Any], name: str, sim_pos: Positions,
                  at: Any) -> list[str]:
    from labrunner.sims.chamber_plant import ChamberParams
    from labrunner.sims.table_plant import TableParams
    from labrunner.sims.world import ImuThermalParams, SimLabConfig

    p = procedure.model
    problems: list[str] = []
    defaults = SimLabConfig()
    imu_rate = float(sim.get("imu_rate_hz", defaults.imu_rate_hz))
    if abs(imu_rate - p.sample_rate_hz) > 1e-9 * max(imu_rate, 1.0):
        problems.append(f"{at('sample_rate_hz')}: sample_rate_hz {p.sample_rate_hz:g} Hz is not the simulated "
                        f"IMU's rate ({name}: imu_rate_hz {imu_rate:g} Hz); every record would miss frames")
    chamber = {**vars(ChamberParams()), **(sim.get("chamber") or {})}
    lo, hi = float(chamber["setpoint_min_c"]), float(chamber["setpoint_max_c"])
    temps = p.temperatures.values() + [p.remount_c]
    outside = [t for t in temps if not lo <= t <= hi]
    if outside:
        key = "remount_c" if outside[0] == p.remount_c and outside[0] not in temps[:-1] else "temperatures"
        problems.append(f"{at(key)}: {key} {outside[0]:g} C is outside the simulated controller's setpoint "
                        f"range {lo:g}..{hi:g} C ({name}: chamber.setpoint_min_c/setpoint_max_c); preflight "
                        "would refuse it")
    ambient = float(chamber["ambient_c"])
    s = p.safety
    if not s.chamber_min_c <= ambient <= s.chamber_max_c:
        problems.append(f"{at('safety')}: the simulated chamber starts at {ambient:g} C ({name}: chamber.ambient_c), "
                        f"outside safety.chamber_min_c..chamber_max_c ({s.chamber_min_c:g}..{s.chamber_max_c:g} C): "
                        "the chamber interlock would trip at the first reading")
    thermal = {**vars(ImuThermalParams()), **(sim.get("imu_thermal") or {})}
    warmest = max(temps + [ambient]) + float(thermal["self_heat_c"])
    if s.imu_max_temp_c <= warmest:
        problems.append(f"{at('safety', 'imu_max_temp_c')}: safety.imu_max_temp_c {s.imu_max_temp_c:g} C: the "
                        f"simulated IMU reaches {warmest:g} C (the plan's warmest temperature plus its self-heating, "
                        f"{name}: imu_thermal.self_heat_c); the IMU interlock would trip")
    table = {**vars(TableParams()), **(sim.get("table") or {})}
    fastest = max(abs(r) for r in p.rates.values())
    if fastest > float(table["max_rate_dps"]):
        problems.append(f"{at('rates')}: rates {fastest:g} deg/s exceed the simulated table's maximum "
                        f"{float(table['max_rate_dps']):g} deg/s ({name}: table.max_rate_dps); preflight would "
                        "refuse it")
    if sim.get("orientation") is not None:
        problems.append(f"{_at(name, sim_pos, 'orientation')}: orientation is not used by a dry run (the "
                        "procedure's first orientation is mounted at the start); it is for `labrunner sim serve`: "
                        "remove it")
    n_steps = len(procedure.steps())
    faults = sim.get("faults") or {}
    for plan in ("schedule", "random"):
        for i, item in enumerate(faults.get(plan) or []):
            step = item.get("at_step")
            if step is not None and step >= n_steps:
                problems.append(f"{_at(name, sim_pos, 'faults', plan, i, 'at_step')}: faults.{plan}[{i}].at_step "
                                f"{step} is beyond the procedure's last step ({n_steps - 1}): it would never fire")
    return problems


def _lab_problems(procedure: Procedure, lab: LabConfig, name: str, lab_pos: Positions, at: Any) -> list[str]:
    p = procedure.model
    problems: list[str] = []
    imu = _section(lab, "imu")
    rate = getattr(imu, "rate_hz", None)
    if isinstance(rate, (int, float)) and abs(rate - p.sample_rate_hz) > 1e-9 * max(rate, 1.0):
        problems.append(f"{at('sample_rate_hz')}: sample_rate_hz {p.sample_rate_hz:g} Hz is not the IMU's rate "
                        f"({name}: imu.rate_hz {rate:g} Hz); every record would miss frames")
    chamber = _section(lab, "chamber")
    profile = getattr(chamber, "profile", None)
    if profile is not None:
        from labrunner.drivers.chamber_profiles import profile_from

        fixed = profile_from(profile).fixed_range_c
        if fixed is not None:
            lo, hi = fixed
            temps = p.temperatures.values() + [p.remount_c]
            outside = [t for t in temps if not lo <= t <= hi]
            if outside:
                problems.append(f"{at('temperatures')}: temperature {outside[0]:g} C is outside the controller's "
                                f"setpoint range {lo:g}..{hi:g} C ({_at(name, lab_pos, 'chamber', 'profile')}: "
                                "profile fixed_range_c); preflight would refuse it")
    return problems


def _section(lab: LabConfig, kind: str) -> Any:
    """An instrument's validated section, whichever way the lab configuration holds it."""
    section = getattr(lab, "section", None)
    if callable(section):
        return section(kind)
    return getattr(lab, kind)


__all__ = ["run_problems", "validate_run"]
