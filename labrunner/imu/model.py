"""The simulated IMU's error model: the paper's Eq. 1 with thermal terms, plus switchable effects.

    y = (I + S(T)) u + b(T) + effects + w

for the accelerometer triad (u = specific force, g) and the gyro triad (u = angular
rate, deg/s); S holds scale-factor errors on its diagonal and misalignment off it,
b is the bias, each element a cubic in (T - T_REF_C) (`baseline.py`). T is the
temperature that drives the errors: the IMU's temperature sensor, or the temperature of
an effect that moves it (a thermal lag's element temperature).

The effects are the classes of `labrunner.imu.effects`, one file each, off by default,
with their parameters in the sensor's own units; the error without noise is the baseline
plus the sum of the model's effects. This one model is used by the simulated IMU
(streaming, with carried state), by the campaign synthesizer, and by
`labrunner.discrepancy` to fit the same model to measured data.
"""

from __future__ import annotations

import copy
import json
import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from labrunner.domain import (  # noqa: F401  (re-exported: the model's vocabulary)
    ACCEL_CHANNELS,
    CHANNELS,
    GYRO_CHANNELS,
    ORIENTATIONS,
    STANDARD_GRAVITY,
    T_REF_C,
    UP_VECTORS,
    orientation_index,
    up_vector,
)

from .baseline import N_COEF, POLY_ORDER, TriadModel, baseline_design, thermal_powers  # noqa: F401 (re-exported)
from .effect import Effect, Stream
from .effects import REGISTRY, effect_class
from .inputs import ImuInputs

log = logging.getLogger(__name__)

# name -> effect class, a live view of the registry (kept for callers of the former table).
EFFECT_TYPES: Mapping[str, type[Effect]] = MappingProxyType(REGISTRY)


@dataclass
class ModelState:
    """What carries over between consecutive chunks of a stream."""

    t_s: float | None = None
    temp_c: float | None = None
    carried: dict[str, Any] = field(default_factory=dict)  # effect name -> the state it carries on


@dataclass
class ImuModel:
    """Error model of a six-axis IMU."""

    accel: TriadModel
    gyro: TriadModel
    effects: dict[str, Any] = field(default_factory=dict)  # name -> effect (an `Effect`, or its parameters)
    seed: int = 0

    def __post_init__(self) -> None:
        for name, eff in list(self.effects.items()):
            cls = effect_class(name)
            if isinstance(eff, Mapping):
                self.effects[name] = cls.from_dict(eff)
            elif not isinstance(eff, cls):
                raise ValueError(f"effect {name!r} must be a {cls.__name__} or its parameters, "
                                 f"not {type(eff).__name__}")

    # -- the pieces ---------------------------------------------------------------------

    def active(self) -> list[Effect]:
        """The model's effects in registry order (the order they are summed in)."""
        return [self.effects[name] for name in REGISTRY if name in self.effects]

    def _mover(self) -> Effect | None:
        return next((e for e in self.active() if e.moves_baseline_temperature), None)

    def element_temperature(self, inputs: ImuInputs, state: ModelState | None = None) -> np.ndarray:
        """Temperature of the sensing element (the IMU sensor's unless an effect moves it)."""
        mover = self._mover()
        temp = np.asarray(inputs.temp_c, dtype=float)
        if mover is None:
            return temp
        st = state or ModelState()
        return mover.baseline_temperature(inputs, st.t_s, st.temp_c, st.carried.get(mover.name))

    def run_offsets(self, runs: np.ndarray) -> np.ndarray:
        """(N, 6) per-run offsets of the effects that have them (one draw per (seed, run))."""
        out = np.zeros((np.asarray(runs).size, len(CHANNELS)))
        for eff in self.active():
            if hasattr(eff, "run_offsets"):
                out += eff.run_offsets(runs, self.seed)
        return out

    def baseline_error(self, temp_c: np.ndarray, inputs: ImuInputs) -> np.ndarray:
        """(N, 6) baseline error S(T) u + b(T) of both triads at temperatures temp_c."""
        n = len(inputs)
        force = np.asarray(inputs.force_g, dtype=float).reshape(n, 3)
        rate = np.asarray(inputs.rate_dps, dtype=float).reshape(n, 3)
        powers = thermal_powers(temp_c)  # the two triads share the temperatures' powers
        out = np.empty((n, 6))
        out[:, :3] = self.accel.error_at_powers(powers, force)
        out[:, 3:] = self.gyro.error_at_powers(powers, rate)
        return out

    def deterministic_error(
        self, inputs: ImuInputs, state: ModelState | None = None, rng: np.random.Generator | None = None
    ) -> tuple[np.ndarray, ModelState]:
        """(N, 6) error without white noise (random walk included when rng is given), and the new state:
        the baseline at the sensor's temperature plus the sum of the model's effects."""
        n = len(inputs)
        temp = np.asarray(inputs.temp_c, dtype=float)
        t = np.asarray(inputs.t_s, dtype=float)
        new = ModelState() if state is None else _copy_state(state)
        if n == 0:
            return np.zeros((0, 6)), new
        st = state or ModelState()
        effects = self.active()
        element = self.element_temperature(inputs, state) if effects else temp
        err = self.baseline_error(temp, inputs)
        for eff in effects:
            stream = Stream(inputs=inputs, element_c=element, baseline_at=lambda tc: self.baseline_error(tc, inputs),
                            seed=int(self.seed), rng=rng, t0=st.t_s, temp0=st.temp_c,
                            carried=st.carried.get(eff.name))
            extra, carried = eff.forward(stream)
            err += extra
            if carried is not None:
                new.carried[eff.name] = carried
        new.t_s = float(t[-1])
        new.temp_c = float(temp[-1])
        return err, new

    def noise_sigma(self, sample_rate_hz: float) -> np.ndarray:
        """Per-sample white-noise standard deviation for each channel at a sample rate."""
        bw = np.sqrt(sample_rate_hz / 2.0)
        return np.array([self.accel.noise_density * bw] * 3 + [self.gyro.noise_density * bw] * 3)

    def simulate(
        self,
        inputs: ImuInputs,
        sample_rate_hz: float,
        rng: np.random.Generator | None,
        state: ModelState | None = None,
    ) -> tuple[np.ndarray, ModelState]:
        """(N, 6) outputs [accel g, gyro deg/s] with noise (none when rng is None), and the new state."""
        err, new = self.deterministic_error(inputs, state, rng)
        # out = truth + err, truth = [force | rate]: added into err (a new array), the same sums bit for bit
        # (addition commutes), column by column (an (n, 3) half of an (n, 6) array is a loop of 3 per row).
        out = err
        _add_truth(out[:, :3], inputs.force_g)
        _add_truth(out[:, 3:], inputs.rate_dps)
        if rng is not None:
            noise = rng.standard_normal(out.shape)
            noise *= self.noise_sigma(sample_rate_hz)[None, :]
            out += noise
        return out, new

    # -- serialisation --------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        return {
            "t_ref_c": T_REF_C,
            "seed": int(self.seed),
            "accel": {"bias": self.accel.bias.tolist(), "scale": self.accel.scale.tolist(),
                      "noise_density": self.accel.noise_density},
            "gyro": {"bias": self.gyro.bias.tolist(), "scale": self.gyro.scale.tolist(),
                     "noise_density": self.gyro.noise_density},
            "effects": {name: effect_to_dict(eff) for name, eff in self.effects.items()},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ImuModel:
        if float(data.get("t_ref_c", T_REF_C)) != T_REF_C:
            raise ValueError(f"IMU model t_ref_c must be {T_REF_C}")
        base = default_imu_model()
        acc = data.get("accel", {})
        gyr = data.get("gyro", {})
        return cls(
            accel=TriadModel(np.asarray(acc.get("bias", base.accel.bias)),
                             np.asarray(acc.get("scale", base.accel.scale)),
                             float(acc.get("noise_density", base.accel.noise_density))),
            gyro=TriadModel(np.asarray(gyr.get("bias", base.gyro.bias)), np.asarray(gyr.get("scale", base.gyro.scale)),
                            float(gyr.get("noise_density", base.gyro.noise_density))),
            effects={k: effect_from_dict(k, v) for k, v in (data.get("effects") or {}).items()},
            seed=int(data.get("seed", 0)),
        )

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2))

    @classmethod
    def load(cls, path: str | Path) -> ImuModel:
        """Load a model written by `save` (JSON) or a YAML file of the same shape."""
        from labrunner.yaml_config import load_yaml, read_text  # the one reader: size, encoding, aliases, duplicates

        text = read_text(path)
        if str(path).endswith((".yaml", ".yml")):
            data, _ = load_yaml(text, str(path))
        else:
            data = json.loads(text)
        if not isinstance(data, Mapping):
            raise ValueError(f"{path}: an IMU model must be a mapping")
        return cls.from_dict(data)

    def with_effects(self, **effects: Any) -> ImuModel:
        """A copy with effects added or replaced (None removes one)."""
        out = copy.deepcopy(self)
        for name, eff in effects.items():
            if eff is None:
                out.effects.pop(name, None)
            else:
                out.effects[name] = effect_from_dict(name, eff) if isinstance(eff, Mapping) else eff
        out.__post_init__()
        return out


def _add_truth(out: np.ndarray, truth: Any) -> None:
    """out += truth for an (n, 3) view, column by column; a broadcast truth (one vector for every sample,
    as the simulated IMU's force) is added as the scalars it repeats: the same sums."""
    n = out.shape[0]
    if n == 0:
        return
    u = np.asarray(truth, dtype=float).reshape(n, 3)
    for j in range(3):
        col = out[:, j]
        np.add(col, u[0, j] if u.strides[0] == 0 else u[:, j], out=col)


def _copy_state(state: ModelState) -> ModelState:
    """A copy the effects may update: their carried states deep-copied (the times and temperatures are floats;
    a stream without effects carries nothing, and deep-copying the empty state was most of a chunk's copy cost)."""
    return ModelState(t_s=state.t_s, temp_c=state.temp_c,
                      carried=copy.deepcopy(state.carried) if state.carried else {})


def effect_to_dict(eff: Effect) -> dict[str, Any]:
    return eff.to_dict()


def effect_from_dict(name: str, data: Mapping[str, Any]) -> Effect:
    """An effect from its JSON parameters, validated (ValueError naming what is wrong)."""
    return effect_class(name).from_dict(data)


def _cubic(c0: float, c1: float, c2: float, c3: float) -> list[float]:
    return [c0, c1, c2, c3]


def default_imu_model(seed: int = 0) -> ImuModel:
    """An IMU like the paper's (LSM303DLHC + L3GD20): magnitudes from its Table 1 and Figs. 3-6.

    Accelerometer z bias moves from about +110 mg at -25 C to -80 mg at 55 C (the
    paper's -2.3 mg/C average); gyro biases move about 0.02-0.03 deg/s/C; gyro scale
    factor changes about 2 % over the range, accelerometer about 0.01 %/C.
    """
    accel_bias = [
        _cubic(0.0215, 4.5e-4, 4.0e-6, -1.5e-7),
        _cubic(-0.0120, -3.0e-4, -3.0e-6, 1.0e-7),
        _cubic(0.0100, -3.7125e-3, 2.0e-6, 7.25e-7),
    ]
    accel_scale = [
        [_cubic(4.0e-3, 8.0e-5, 3.0e-7, -1.0e-8), _cubic(2.5e-3, 1.0e-6, 0, 0), _cubic(-1.8e-3, -1.5e-6, 0, 0)],
        [_cubic(-1.2e-3, 1.2e-6, 0, 0), _cubic(-3.0e-3, -6.0e-5, 2.0e-7, 8.0e-9), _cubic(3.1e-3, 1.0e-6, 0, 0)],
        [_cubic(2.2e-3, -2.0e-6, 0, 0), _cubic(-0.9e-3, 1.0e-6, 0, 0), _cubic(6.0e-3, 1.0e-4, -4.0e-7, -1.2e-8)],
    ]
    gyro_bias = [
        _cubic(0.55, 0.022, -1.6e-4, -3.0e-6),
        _cubic(-0.05, -0.018, 2.4e-4, 2.5e-6),
        _cubic(0.70, 0.028, 1.2e-4, -2.0e-6),
    ]
    gyro_scale = [
        [_cubic(1.0e-2, 2.5e-4, -1.5e-6, -3.0e-8), _cubic(4.0e-3, 2.0e-6, 0, 0), _cubic(-2.5e-3, -1.0e-6, 0, 0)],
        [_cubic(-3.5e-3, 1.5e-6, 0, 0), _cubic(-8.0e-3, -2.0e-4, 2.0e-6, 2.0e-8), _cubic(3.0e-3, 2.0e-6, 0, 0)],
        [_cubic(1.5e-3, -1.0e-6, 0, 0), _cubic(-4.0e-3, 1.0e-6, 0, 0), _cubic(1.2e-2, 2.2e-4, 1.0e-6, -2.5e-8)],
    ]
    return ImuModel(
        accel=TriadModel(np.array(accel_bias), np.array(accel_scale), noise_density=220e-6),
        gyro=TriadModel(np.array(gyro_bias), np.array(gyro_scale), noise_density=0.03),
        effects={},
        seed=seed,
    )
