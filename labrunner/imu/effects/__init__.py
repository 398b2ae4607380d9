"""The IMU effects: one module, one class (a subclass of `labrunner.imu.effect.Effect`) each.

Importing this package imports every module in it, and each effect class registers itself
by its `name`; `REGISTRY` holds them in their `order`. The simulator (`ImuModel`), the
diagnosis (`labrunner.discrepancy`: candidates, design, coverage, advice) and the docs'
cause table all read `REGISTRY`, so adding a cause is adding one file here, and deleting
the file removes it everywhere (docs/diagnosis.md, "Adding a cause").
"""

from __future__ import annotations

import importlib
import logging
import pkgutil

from ..effect import Effect, defined_effects

log = logging.getLogger(__name__)


def _discover() -> dict[str, type[Effect]]:
    for info in pkgutil.iter_modules(__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{__name__}.{info.name}")
    found = [cls for cls in defined_effects().values() if cls.__module__.startswith(f"{__name__}.")]
    log.debug("IMU effects: %s", ", ".join(c.name for c in found))
    return {cls.name: cls for cls in sorted(found, key=lambda c: (c.order, c.name))}


REGISTRY: dict[str, type[Effect]] = _discover()


def effect_class(name: str) -> type[Effect]:
    """The class of a registered effect (ValueError naming the known ones otherwise)."""
    if name not in REGISTRY:
        raise ValueError(f"unknown effect {name!r}; expected one of {', '.join(REGISTRY)}")
    return REGISTRY[name]


def candidate_causes() -> dict[str, type[Effect]]:
    """The effects the diagnosis tests, in registry order."""
    return {name: cls for name, cls in REGISTRY.items() if cls.candidate}


def drift_effect() -> type[Effect] | None:
    """The effect that reproduces the random-walk drift of the diagnosis's noise model, if any."""
    return next((cls for cls in REGISTRY.values() if cls.represents_drift), None)


__all__ = ["REGISTRY", "Effect", "candidate_causes", "drift_effect", "effect_class"]
