"""The one reader of sim configurations (seed, plants, IMU model, faults) for run, check and sim serve.

A sim configuration is kept as the mapping the user wrote (it is stored with a dry-run campaign,
and a resumed dry run rebuilds its simulated lab from it), validated here against the simulated
world and the fault-plan format, with errors naming the file and line.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labrunner.yaml_config import ConfigError, load_yaml, read_text

if TYPE_CHECKING:
    from labrunner.sims.world import SimLabConfig

log = logging.getLogger(__name__)


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
    try:
        _validate(data)
    except (ValueError, TypeError, OSError) as exc:
        line = positions.get(("faults",), 1) if "fault" in str(exc) else 1
        raise ConfigError([f"{name}:{line}: {exc}"]) from None
    log.debug("sim configuration from %s: keys %s", name, sorted(data))
    return data


def _validate(data: dict[str, Any]) -> None:
    from labrunner.fault_plan import Fault
    from labrunner.sims.world import SimLabConfig

    SimLabConfig.from_dict(data)
    faults = data.get("faults") or {}
    if not isinstance(faults, dict):
        raise ValueError("faults must be a mapping")
    for key in ("schedule", "random"):
        items = faults.get(key) or []
        if not isinstance(items, list):
            raise ValueError(f"faults.{key} must be a list")
        for i, item in enumerate(items):
            if not isinstance(item, dict):
                raise ValueError(f"faults.{key}[{i}] must be a mapping with at_s, kind, duration_s or count")
            try:
                Fault(**item)
            except TypeError as exc:
                raise ValueError(f"faults.{key}[{i}]: {exc}") from None


def load_sim_config(source: str | Path | dict[str, Any] | None) -> SimLabConfig:
    """The validated `SimLabConfig` of a sim configuration (path or mapping)."""
    from labrunner.sims.world import SimLabConfig

    return SimLabConfig.from_dict(sim_config_dict(source))


def has_fault_plan(sim_dict: dict[str, Any] | None) -> bool:
    """Whether a sim configuration schedules faults during the campaign (random or at given times)."""
    faults = (sim_dict or {}).get("faults") or {}
    return bool(faults.get("random") or faults.get("schedule"))
