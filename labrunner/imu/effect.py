"""One IMU effect, everything about it in one class: the base class and what its methods see.

An effect (a subclass of `Effect` in a module of `labrunner.imu.effects`) owns

- its parameters: dataclass fields, validated (`validate`), to and from JSON (`to_dict`,
  `from_dict`);
- the error the simulator adds (`forward`, with whatever state it carries from one chunk of
  a stream to the next);
- its regressors for the diagnosis, linear in its coefficients once its nonlinear
  parameters are fixed (`regressors` at row level; `block_regressors` and `predict` where
  the diagnosis needs them cheaper), and its own coefficients at given parameters
  (`theta`, `coefficients`), so forward error == regressors x coefficients can be checked;
- its nonlinear parameter grid and bounds for the campaign at hand (`nonlinear`);
- the campaign coverage it needs to be identifiable, with the sentence for
  `not_identifiable` (`coverage_gaps`);
- the measurement that separates it from its usual confounders (`separates`);
- how fitted coefficients become its JSON parameters and the simulator effect that
  reproduces them (`summarize`);
- a one-line description and its JSON parameters for the docs' cause table.

Subclasses register themselves by name; `labrunner.imu.effects` imports every module of
its package, so one file is one effect (docs/diagnosis.md, "Adding a cause").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np

from labrunner.domain import CHANNELS

from .inputs import ImuInputs

# A logged temperature changing slower than this is not a ramp (campaign coverage).
RAMP_C_PER_MIN = 0.1

_DEFINED: dict[str, type[Effect]] = {}  # every subclass with a name, in definition order


def defined_effects() -> dict[str, type[Effect]]:
    """Effect classes defined so far (use `labrunner.imu.effects.REGISTRY`, which imports them all)."""
    return dict(_DEFINED)


# --- what the methods see --------------------------------------------------------------------


@dataclass
class Stream:
    """One chunk of samples as an effect's forward error sees it, and where the stream left off."""

    inputs: ImuInputs
    element_c: np.ndarray  # temperature that drives the thermal terms (lagged when an effect moves it)
    baseline_at: Callable[[np.ndarray], np.ndarray]  # (N, 6) baseline error with its thermal terms at temperatures
    seed: int  # the model's seed (per-run draws)
    rng: np.random.Generator | None  # stochastic effects draw from it; None: leave them out
    t0: float | None = None  # last sample time of the previous chunk
    temp0: float | None = None  # and its sensor temperature
    carried: Any = None  # this effect's state after the previous chunk (None at the start)


class RowData(Protocol):
    """Row data the regressors are built from (`Measurements` and `ImuInputs` have these)."""

    @property
    def t_s(self) -> np.ndarray: ...
    @property
    def run(self) -> np.ndarray: ...
    @property
    def t_on_s(self) -> np.ndarray: ...
    @property
    def temp_c(self) -> np.ndarray: ...
    @property
    def force_g(self) -> np.ndarray: ...
    @property
    def rate_dps(self) -> np.ndarray: ...


class BlockMeans(Protocol):
    @property
    def run(self) -> np.ndarray: ...  # (M,) run of each block

    def mean(self, values: np.ndarray) -> np.ndarray: ...


class FitContext(Protocol):
    """What the diagnosis knows about a campaign when it builds an effect's regressors."""

    @property
    def rows(self) -> RowData: ...
    @property
    def blocks(self) -> BlockMeans: ...
    @property
    def run_ids(self) -> np.ndarray: ...  # sorted runs in the data
    @property
    def remounts(self) -> np.ndarray: ...  # rows where the IMU was remounted
    @property
    def path_via_c(self) -> float | None: ...  # the unlogged temperature path passes here at the start and remounts
    @property
    def rng(self) -> np.random.Generator | None: ...  # the draws of a stochastic effect's regressors
    @property
    def temp_min(self) -> float: ...
    @property
    def temp_max(self) -> float: ...
    @property
    def min_lag_s(self) -> float: ...  # shortest lag the temperature log resolves
    @property
    def min_travel_c(self) -> float: ...  # smallest hysteresis travel it resolves
    @property
    def ramps_logged(self) -> bool: ...

    def element_temp(self, tau_s: float | None) -> np.ndarray: ...


class CampaignFacts(Protocol):
    """Facts about a campaign's design an effect's identifiability depends on (`Coverage` has them)."""

    @property
    def runs(self) -> int: ...
    @property
    def orientations(self) -> list[str]: ...
    @property
    def rotating(self) -> bool: ...
    @property
    def vertical(self) -> tuple[bool, bool, bool]: ...  # each body axis was vertical in some orientation
    @property
    def both_ways(self) -> tuple[bool, bool, bool]: ...  # ... and both up and down
    @property
    def bias_separable(self) -> bool: ...  # the orientations separate accelerometer bias from scale factor
    @property
    def max_temperature_rate_c_per_min(self) -> float: ...
    @property
    def branch_overlap_c(self) -> float: ...
    @property
    def branch_rows(self) -> tuple[int, int]: ...  # (heating rows, cooling rows inside the range heated through)
    @property
    def temperature_levels(self) -> int: ...
    @property
    def power_ons_within_an_orientation(self) -> int: ...


@dataclass(frozen=True)
class Nonlinear:
    """A nonlinear parameter searched on a grid, then refined."""

    name: str
    grid: tuple[float, ...]
    log: bool = True  # refine on a log scale (time constants, travels)


@dataclass(frozen=True)
class Gap:
    """What a campaign cannot show about an effect: a sentence, and the channels it cannot be
    tested on (none: the effect is still tested, the sentence only qualifies it)."""

    message: str
    channels: tuple[str, ...] = ()


@dataclass
class Fit:
    """An effect's fit on the channels it was selected for (whitened-GLS quantities)."""

    theta: dict[str, float]
    coef: dict[str, np.ndarray]  # channel -> the effect's coefficients
    cov: dict[str, np.ndarray]  # channel -> their covariance
    schur: dict[str, np.ndarray]  # channel -> Gram of the effect's columns with the rest projected out


# --- channel helpers -------------------------------------------------------------------------


def channel_map(values: Mapping[str, float] | None) -> dict[str, float]:
    """{channel: value}, channels checked."""
    out = {str(k): float(v) for k, v in (values or {}).items()}
    for k in out:
        if k not in CHANNELS:
            raise ValueError(f"unknown channel {k!r}; expected one of {', '.join(CHANNELS)}")
    return out


def channel_vector(values: Mapping[str, float]) -> np.ndarray:
    """(6,) values in channel order, 0 where absent."""
    return np.array([values.get(c, 0.0) for c in CHANNELS])


def same_for(channels: tuple[str, ...], col: np.ndarray) -> dict[str, np.ndarray]:
    """The same regressors for several channels (one shared array: the diagnosis whitens it once)."""
    col = col.reshape(col.shape[0], -1)
    return {c: col for c in channels}


def scalars(fit: Fit) -> dict[str, float]:
    """{channel: its one coefficient}."""
    return {c: float(v[0]) for c, v in fit.coef.items()}


def random_channels(rng: np.random.Generator, pool: tuple[str, ...], accel: float, gyro: float,
                    signed: bool = True) -> dict[str, float]:
    """{channel: value} on a random non-empty subset of `pool`, magnitudes up to `accel`/`gyro`."""
    n = int(rng.integers(1, len(pool) + 1))
    chosen = sorted(rng.choice(pool, size=n, replace=False).tolist(), key=CHANNELS.index)
    out = {}
    for c in chosen:
        scale = accel if CHANNELS.index(c) < 3 else gyro
        value = float(rng.uniform(0.2, 1.0)) * scale
        out[c] = value * float(rng.choice([-1.0, 1.0])) if signed else value
    return out


def per_channel(values: Mapping[str, float], channels: tuple[str, ...] = CHANNELS) -> dict[str, np.ndarray]:
    """{channel: (1,) coefficient} for effects with one coefficient per channel."""
    return {c: np.array([float(values.get(c, 0.0))]) for c in channels}


# --- the base class --------------------------------------------------------------------------


@dataclass
class Effect:
    """Base class of the IMU effects (see the module docstring). Subclasses are dataclasses."""

    name: ClassVar[str] = ""
    order: ClassVar[int] = 1000  # place in the registry (the diagnosis tries causes in this order)
    what: ClassVar[str] = ""  # one line: what the effect is
    driver: ClassVar[str] = ""  # what the data must vary to show it (advice on confounding, the docs)
    json_parameters: ClassVar[str] = ""  # its parameters in the diagnosis JSON (the docs' cause table)
    acts_on: ClassVar[tuple[str, ...]] = CHANNELS  # channels it can act on
    candidate: ClassVar[bool] = True  # a cause the diagnosis tests
    moves_baseline_temperature: ClassVar[bool] = False  # drives the baseline with its own temperature
    lag_parameter: ClassVar[str] = ""  # ... by a lag with this nonlinear parameter (s)
    uses_element_temperature: ClassVar[bool] = False  # its regressors depend on that temperature
    per_channel_columns: ClassVar[bool] = False  # regressors differ from channel to channel
    represents_drift: ClassVar[bool] = False  # the random-walk drift the diagnosis estimates as noise
    separates: ClassVar[dict[str, str]] = {}  # other effect -> the measurement that tells the two apart

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("name"):
            _DEFINED[cls.name] = cls

    # -- parameters ------------------------------------------------------------------------

    def validate(self) -> None:
        """Check and normalise the fields (raise ValueError with the effect's name)."""

    @classmethod
    def random(cls, rng: np.random.Generator) -> Effect:
        """An instance at random, realistic parameters (the per-effect agreement tests draw them)."""
        raise NotImplementedError(f"effect {cls.name!r} does not say how to draw random parameters")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Effect:
        if not isinstance(data, Mapping):
            raise ValueError(f"effect {cls.name!r}: parameters must be a mapping")
        try:
            eff = cls(**dict(data))
        except TypeError as exc:
            raise ValueError(f"effect {cls.name!r}: {exc}") from None
        eff.validate()
        return eff

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    # -- the simulator -----------------------------------------------------------------------

    def forward(self, stream: Stream) -> tuple[np.ndarray, Any]:
        """(N, 6) error this effect adds to a chunk of samples, and the state it carries on."""
        raise NotImplementedError

    def baseline_temperature(self, inputs: ImuInputs, t0: float | None, temp0: float | None,
                             carried: Any) -> np.ndarray:
        """The temperature that drives the thermal terms, for an effect that moves it."""
        raise NotImplementedError

    # -- the diagnosis -------------------------------------------------------------------------

    @classmethod
    def nonlinear(cls, ctx: FitContext) -> tuple[Nonlinear, ...]:
        """Nonlinear parameters and their grids, suited to the campaign."""
        return ()

    @classmethod
    def regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                   ) -> dict[str, np.ndarray]:
        """channel -> (N, q) row-level regressors at nonlinear parameters theta."""
        raise NotImplementedError

    @classmethod
    def block_regressors(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None
                         ) -> dict[str, np.ndarray] | None:
        """channel -> (M, q) block means of the regressors when cheaper than averaging rows (else None)."""
        return None

    @classmethod
    def predict(cls, ctx: FitContext, theta: dict[str, float], element_tau: float | None, channel: str,
                coef: np.ndarray) -> np.ndarray:
        """(N,) contribution to a channel's error for given coefficients."""
        return cls.regressors(ctx, theta, element_tau)[channel] @ coef

    @classmethod
    def envelope(cls, ctx: FitContext) -> dict[str, np.ndarray]:
        """channel -> (N, k) row-level columns spanning a rough version of the effect over its
        parameter range, for the diagnosis's drift estimate (none: {}). For an effect that moves
        the baseline's temperature: the element's temperature offsets (the diagnosis turns them
        into error columns with the baseline's fitted temperature derivatives)."""
        return {}

    @classmethod
    def has_signature(cls) -> bool:
        """Whether `consistent` checks more than the fit (the diagnosis then calls it)."""
        return cls.consistent.__func__ is not Effect.consistent.__func__  # type: ignore[attr-defined]

    @classmethod
    def consistent(cls, coef: np.ndarray, schur: np.ndarray) -> bool:
        """Whether a fitted channel's coefficients (and Schur complement) show the effect's own
        signature beyond fitting well; False rejects the channel."""
        return True

    @classmethod
    def coverage_gaps(cls, facts: CampaignFacts) -> list[Gap]:
        """What this campaign cannot show about the effect."""
        return []

    @classmethod
    def rate_floor(cls, channel: str, max_rate_dps: float, rate_accuracy: float) -> float:
        """Peak-to-peak size on a channel below which the rate table's own accuracy could fake the effect."""
        return 0.0

    @classmethod
    def resolution_limit(cls, ctx: FitContext) -> str | None:
        """The part of the effect a coarse temperature log cannot resolve (a phrase), if any."""
        return None

    @classmethod
    def notes(cls, ctx: FitContext) -> list[str]:
        """Qualifications of the diagnosis of this effect in this campaign."""
        return []

    @classmethod
    def summarize(cls, fit: Fit, ctx: FitContext) -> tuple[dict[str, Any], dict[str, Any]]:
        """(parameters for the JSON, keyword arguments of the simulator effect that reproduces them)."""
        raise NotImplementedError

    @classmethod
    def from_drift(cls, drift_per_sqrt_s: dict[str, float]) -> dict[str, Any]:
        """For the effect that `represents_drift`: keyword arguments reproducing a drift the
        diagnosis estimated per channel (sensor units per sqrt(s))."""
        raise NotImplementedError

    def theta(self) -> dict[str, float]:
        """This instance's nonlinear parameters (as `regressors` takes them)."""
        return {p: float(getattr(self, p)) for p in self.nonlinear_names()}

    @classmethod
    def nonlinear_names(cls) -> tuple[str, ...]:
        return ()

    def coefficients(self, ctx: FitContext, seed: int) -> dict[str, np.ndarray]:
        """channel -> this instance's coefficients of `regressors(ctx, self.theta(), ...)`."""
        raise NotImplementedError

    def intercept(self, ctx: FitContext, seed: int) -> np.ndarray:
        """(6,) the part of the forward error the baseline's bias constant holds in the diagnosis."""
        return np.zeros(len(CHANNELS))
