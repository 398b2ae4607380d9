"""The simulated IMU's error model: the paper's Eq. 1 with thermal terms, plus switchable effects.

    y = (I + S(T)) u + b(T) + effects + w

for the accelerometer triad (u = specific force, g) and the gyro triad (u = angular
rate, deg/s); S holds scale-factor errors on its diagonal and misalignment off it,
b is the bias, each element a cubic in (T - T_REF_C). T is the temperature that
drives the errors: the IMU's temperature sensor, or with `thermal_lag` the sensing
element's temperature lagging it.

This one module is used by the simulated IMU (streaming, with carried state), by
the campaign synthesizer, and by `labrunner.discrepancy` to fit the same model to
measured data. Every effect of DESIGN.md's diagnosis table is a term here, off by
default, with its parameters in the sensor's own units.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
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

from .recursions import first_order_lag, play_state

POLY_ORDER = 3  # cubic thermal terms: coefficients c0..c3 of (T - T_REF_C)**k
N_COEF = POLY_ORDER + 1


def thermal_powers(temp_c: np.ndarray) -> np.ndarray:
    """(N, 4) matrix of (T - T_REF_C)**k, k = 0..3."""
    tau = np.asarray(temp_c, dtype=float) - T_REF_C
    return np.stack([np.ones_like(tau), tau, tau * tau, tau * tau * tau], axis=-1)


def baseline_design(temp_c: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N, 16) regressors of one triad's baseline error for one output channel.

    The error of channel i is design @ coef[i], with coef[i] laid out as
    [bias c0..c3, S[i,0] c0..c3, S[i,1] c0..c3, S[i,2] c0..c3]; the design is the
    same for the three channels of a triad.
    """
    p = thermal_powers(temp_c)
    u = np.asarray(reference, dtype=float)
    return np.concatenate([p, p * u[:, 0:1], p * u[:, 1:2], p * u[:, 2:3]], axis=1)


@dataclass
class TriadModel:
    """Thermal error terms of one sensor triad."""

    bias: np.ndarray  # (3, 4): b_i(T) coefficients, sensor units
    scale: np.ndarray  # (3, 3, 4): S_ij(T) coefficients, unitless
    noise_density: float  # white noise, sensor units per sqrt(Hz)

    def __post_init__(self) -> None:
        self.bias = np.asarray(self.bias, dtype=float).reshape(3, N_COEF)
        self.scale = np.asarray(self.scale, dtype=float).reshape(3, 3, N_COEF)

    def coefficients(self) -> np.ndarray:
        """(3, 16) coefficients matching `baseline_design`."""
        return np.concatenate([self.bias, self.scale[:, 0], self.scale[:, 1], self.scale[:, 2]], axis=1)

    @classmethod
    def from_coefficients(cls, coef: np.ndarray, noise_density: float) -> TriadModel:
        coef = np.asarray(coef, dtype=float).reshape(3, 4 * N_COEF)
        scale = np.stack([coef[:, N_COEF * (1 + j): N_COEF * (2 + j)] for j in range(3)], axis=1)
        return cls(bias=coef[:, :N_COEF], scale=scale, noise_density=noise_density)

    def bias_at(self, temp_c: np.ndarray) -> np.ndarray:
        """(N, 3) bias at temperatures."""
        return thermal_powers(temp_c) @ self.bias.T

    def scale_at(self, temp_c: np.ndarray) -> np.ndarray:
        """(N, 3, 3) S(T)."""
        return np.einsum("nk,ijk->nij", thermal_powers(temp_c), self.scale)

    def error(self, temp_c: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """(N, 3) baseline error S(T) u + b(T)."""
        p = thermal_powers(temp_c)
        u = np.asarray(reference, dtype=float)
        err = p @ self.bias.T
        for j in range(3):
            err += (p @ self.scale[:, j, :].T) * u[:, j: j + 1]
        return err


# --- effects -------------------------------------------------------------------------


def _channel_map(values: Mapping[str, float] | None) -> dict[str, float]:
    out = {str(k): float(v) for k, v in (values or {}).items()}
    for k in out:
        if k not in CHANNELS:
            raise ValueError(f"unknown channel {k!r}; expected one of {', '.join(CHANNELS)}")
    return out


def _channel_vector(values: Mapping[str, float]) -> np.ndarray:
    return np.array([values.get(c, 0.0) for c in CHANNELS])


@dataclass
class ThermalLag:
    """The sensing element lags the IMU temperature sensor by a first-order lag."""

    tau_s: float = 300.0
    channels: list[str] = field(default_factory=lambda: list(CHANNELS))


@dataclass
class Hysteresis:
    """Heating and cooling branches differ: offset = width/2 * h, h in [-1, 1] the branch state."""

    width: dict[str, float] = field(default_factory=dict)  # heating minus cooling, sensor units
    travel_c: float = 2.0  # temperature travel that moves the branch state by 1 - 1/e


@dataclass
class Warmup:
    """A decaying transient after each power-on: amplitude * exp(-t_on / tau)."""

    tau_s: float = 600.0
    amplitude: dict[str, float] = field(default_factory=dict)  # offset at power-on


@dataclass
class TurnOnBias:
    """A different constant offset after each power-on, normal with spread sigma.

    `offsets` pins the offsets of listed runs ({run number: {channel: offset}}), so a model
    fitted to a measured campaign reproduces that campaign's runs; other runs draw from sigma.
    """

    sigma: dict[str, float] = field(default_factory=dict)
    offsets: dict[str, dict[str, float]] = field(default_factory=dict)


@dataclass
class GSensitivity:
    """Gyro output depends on specific force: gyro += M f, M in deg/s per g."""

    matrix_dps_per_g: list[list[float]] = field(default_factory=lambda: [[0.0] * 3 for _ in range(3)])


@dataclass
class ScaleNonlinearity:
    """Output error grows with the square of the input: error = k2 * u_i**2."""

    k2_per_dps: dict[str, float] = field(default_factory=dict)  # per g for accelerometer channels


@dataclass
class TemperatureNonlinearity:
    """Temperature dependence that is not cubic: a smooth step amplitude * tanh((T - centre) / width)."""

    amplitude: dict[str, float] = field(default_factory=dict)
    center_c: float = 10.0
    width_c: float = 4.0


@dataclass
class LeverArm:
    """The accelerometer sits r_m (body frame, metres) off the rotation axis: it senses the
    centripetal acceleration w x (w x r) / g0, which grows with the square of the table rate on
    the horizontal axes. (The tangential term, present only while the table accelerates, is
    neglected.)"""

    r_m: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])



@dataclass
class BiasRandomWalk:
    """Slow random-walk bias drift, sigma in sensor units per sqrt(s) (bias instability)."""

    sigma_per_sqrt_s: dict[str, float] = field(default_factory=dict)


EFFECT_TYPES: dict[str, type] = {
    "thermal_lag": ThermalLag,
    "hysteresis": Hysteresis,
    "warmup": Warmup,
    "turn_on_bias": TurnOnBias,
    "g_sensitivity": GSensitivity,
    "scale_nonlinearity": ScaleNonlinearity,
    "temperature_nonlinearity": TemperatureNonlinearity,
    "bias_random_walk": BiasRandomWalk,
    "lever_arm": LeverArm,
}


@dataclass
class ImuInputs:
    """What the error model needs per sample (all arrays of length N, time-ordered)."""

    t_s: np.ndarray  # time, s (any origin, increasing)
    run: np.ndarray  # power-on counter
    t_on_s: np.ndarray  # time since this run's power-on, s
    temp_c: np.ndarray  # IMU temperature sensor, deg C
    force_g: np.ndarray  # (N, 3) true specific force in the body frame, g
    rate_dps: np.ndarray  # (N, 3) true angular rate in the body frame, deg/s

    def __len__(self) -> int:
        return int(np.asarray(self.t_s).size)


@dataclass
class ModelState:
    """What carries over between consecutive chunks of a stream."""

    t_s: float | None = None
    temp_c: float | None = None
    element_c: float | None = None  # thermal-lag element temperature
    branch: float = 0.0  # hysteresis state
    walk: np.ndarray = field(default_factory=lambda: np.zeros(6))  # random-walk bias per channel


@dataclass
class ImuModel:
    """Error model of a six-axis IMU."""

    accel: TriadModel
    gyro: TriadModel
    effects: dict[str, Any] = field(default_factory=dict)  # name -> effect dataclass
    seed: int = 0

    def __post_init__(self) -> None:
        for name, eff in list(self.effects.items()):
            if name not in EFFECT_TYPES:
                raise ValueError(f"unknown effect {name!r}; expected one of {', '.join(EFFECT_TYPES)}")
            if isinstance(eff, Mapping):
                self.effects[name] = effect_from_dict(name, eff)

    # -- the pieces ---------------------------------------------------------------

    def element_temperature(self, inputs: ImuInputs, state: ModelState | None = None) -> np.ndarray:
        """Temperature of the sensing element (the IMU sensor's unless thermal_lag is on)."""
        lag = self.effects.get("thermal_lag")
        temp = np.asarray(inputs.temp_c, dtype=float)
        if lag is None:
            return temp
        if state is not None and state.element_c is not None:
            return first_order_lag(inputs.t_s, temp, lag.tau_s, y0=state.element_c, x0=state.temp_c, t0=state.t_s)
        return first_order_lag(inputs.t_s, temp, lag.tau_s)

    def run_offsets(self, runs: np.ndarray) -> np.ndarray:
        """(N, 6) turn-on offsets: one normal draw per (seed, run), so every chunk agrees."""
        eff = self.effects.get("turn_on_bias")
        runs = np.asarray(runs, dtype=np.int64)
        out = np.zeros((runs.size, 6))
        if eff is None or runs.size == 0:
            return out
        sigma = _channel_vector(eff.sigma)
        pinned = {int(k): _channel_vector(v) for k, v in eff.offsets.items()}
        for r in np.unique(runs):
            if int(r) in pinned:
                out[runs == r] = pinned[int(r)]
                continue
            z = np.random.default_rng([int(self.seed) & 0xFFFFFFFF, int(r) & 0xFFFFFFFF, 0x7B1A5]).standard_normal(6)
            out[runs == r] = z * sigma
        return out

    def deterministic_error(
        self, inputs: ImuInputs, state: ModelState | None = None, rng: np.random.Generator | None = None
    ) -> tuple[np.ndarray, ModelState]:
        """(N, 6) error without white noise (random walk included when rng is given), and the new state."""
        n = len(inputs)
        force = np.asarray(inputs.force_g, dtype=float).reshape(n, 3)
        rate = np.asarray(inputs.rate_dps, dtype=float).reshape(n, 3)
        temp = np.asarray(inputs.temp_c, dtype=float)
        t = np.asarray(inputs.t_s, dtype=float)
        new = ModelState() if state is None else copy.deepcopy(state)
        if n == 0:
            return np.zeros((0, 6)), new

        element = self.element_temperature(inputs, state)
        lag = self.effects.get("thermal_lag")
        err = np.empty((n, 6))
        if lag is None:
            err[:, :3] = self.accel.error(temp, force)
            err[:, 3:] = self.gyro.error(temp, rate)
        else:
            lagged = np.array([c in lag.channels for c in CHANNELS])
            for sl, triad, u in ((slice(0, 3), self.accel, force), (slice(3, 6), self.gyro, rate)):
                e_lag = triad.error(element, u)
                e_now = triad.error(temp, u)
                err[:, sl] = np.where(lagged[sl], e_lag, e_now)

        eff = self.effects.get("temperature_nonlinearity")
        if eff is not None:
            step = np.tanh((element - eff.center_c) / eff.width_c)
            err += step[:, None] * _channel_vector(eff.amplitude)[None, :]

        eff = self.effects.get("hysteresis")
        if eff is not None:
            h0 = state.branch if state is not None else 0.0
            temp0 = state.temp_c if state is not None else None
            h = play_state(temp, eff.travel_c, h0=h0, temp0=temp0)
            err += 0.5 * h[:, None] * _channel_vector(eff.width)[None, :]
            new.branch = float(h[-1])

        eff = self.effects.get("warmup")
        if eff is not None:
            decay = np.exp(-np.maximum(np.asarray(inputs.t_on_s, dtype=float), 0.0) / eff.tau_s)
            err += decay[:, None] * _channel_vector(eff.amplitude)[None, :]

        if "turn_on_bias" in self.effects:
            err += self.run_offsets(inputs.run)

        eff = self.effects.get("g_sensitivity")
        if eff is not None:
            err[:, 3:] += force @ np.asarray(eff.matrix_dps_per_g, dtype=float).T

        eff = self.effects.get("scale_nonlinearity")
        if eff is not None:
            k2 = _channel_vector(eff.k2_per_dps)
            err += np.concatenate([force, rate], axis=1) ** 2 * k2[None, :]

        eff = self.effects.get("lever_arm")
        if eff is not None:
            w = np.deg2rad(rate)
            r = np.asarray(eff.r_m, dtype=float)
            err[:, :3] += np.cross(w, np.cross(w, r[None, :])) / STANDARD_GRAVITY

        eff = self.effects.get("bias_random_walk")
        if eff is not None and rng is not None:
            sig = _channel_vector(eff.sigma_per_sqrt_s)
            t_prev = np.concatenate(([t[0] if state is None or state.t_s is None else state.t_s], t[:-1]))
            dt = np.maximum(t - t_prev, 0.0)
            steps = rng.standard_normal((n, 6)) * np.sqrt(dt)[:, None] * sig[None, :]
            walk = new.walk[None, :] + np.cumsum(steps, axis=0)
            err += walk
            new.walk = walk[-1].copy()

        new.t_s = float(t[-1])
        new.temp_c = float(temp[-1])
        new.element_c = float(element[-1])
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
        truth = np.concatenate([np.asarray(inputs.force_g, float), np.asarray(inputs.rate_dps, float)], axis=1)
        out = truth + err
        if rng is not None:
            out += rng.standard_normal(out.shape) * self.noise_sigma(sample_rate_hz)[None, :]
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
            accel=TriadModel(np.asarray(acc.get("bias", base.accel.bias)), np.asarray(acc.get("scale", base.accel.scale)),
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
        text = Path(path).read_text()
        if str(path).endswith((".yaml", ".yml")):
            import yaml

            data = yaml.safe_load(text)
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


def effect_to_dict(eff: Any) -> dict[str, Any]:
    from dataclasses import asdict

    return asdict(eff)


def effect_from_dict(name: str, data: Mapping[str, Any]) -> Any:
    if name not in EFFECT_TYPES:
        raise ValueError(f"unknown effect {name!r}; expected one of {', '.join(EFFECT_TYPES)}")
    cls = EFFECT_TYPES[name]
    try:
        eff = cls(**dict(data))
    except TypeError as exc:
        raise ValueError(f"effect {name!r}: {exc}") from None
    for attr in ("width", "amplitude", "sigma", "k2_per_dps", "sigma_per_sqrt_s"):
        if hasattr(eff, attr):
            setattr(eff, attr, _channel_map(getattr(eff, attr)))
    if isinstance(eff, ThermalLag):
        for c in eff.channels:
            if c not in CHANNELS:
                raise ValueError(f"effect thermal_lag: unknown channel {c!r}")
        if eff.tau_s <= 0:
            raise ValueError("effect thermal_lag: tau_s must be > 0")
    if isinstance(eff, TurnOnBias):
        try:
            eff.offsets = {str(int(k)): _channel_map(v) for k, v in (eff.offsets or {}).items()}
        except (TypeError, ValueError) as exc:
            raise ValueError(f"effect turn_on_bias: offsets must map run numbers to channel offsets ({exc})") from None
    if isinstance(eff, LeverArm):
        r = np.asarray(eff.r_m, dtype=float)
        if r.shape != (3,):
            raise ValueError("effect lever_arm: r_m must be 3 numbers (metres, body frame)")
        eff.r_m = r.tolist()
    if isinstance(eff, GSensitivity):
        m = np.asarray(eff.matrix_dps_per_g, dtype=float)
        if m.shape != (3, 3):
            raise ValueError("effect g_sensitivity: matrix_dps_per_g must be 3x3")
        eff.matrix_dps_per_g = m.tolist()
    return eff


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
