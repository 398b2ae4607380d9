"""Generated logs that look like a real motionless thermal log, written independently of the simulator.

Nothing here uses `labrunner.imu` or `labrunner.sims`: the temperature path, the error curves and the
noise are this file's own, so a diagnosis that passes on them is not just inverting its own
simulator. A log is 1 Hz rows, three orientations, slow heating and cooling between soaks, the IMU
temperature sensor jittering (0.01-0.05 degC) and rounded to 1/16 degC, the outputs carrying white
noise, bias instability (flicker noise, made as a sum of first-order Markov processes over five
decades of correlation time) and a rate random walk. Switches hide one situation at a time:

- `hysteresis`: heating and cooling branches apart by `width` (a play operator of `travel_c`);
- `run_offsets`: a constant offset per `run` label, large against the noise;
- `continuous`: one recording, `run` labels change without a gap and without a power-on;
- `power_on_column`: write the optional `power_on` column (1 on the first row after each power-on).

`LogTruth` keeps what was hidden, for the test to compare with after the diagnosis saw the rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

ORIENTS = ("x_up", "y_up", "z_up")
UP = {"x_up": (1.0, 0.0, 0.0), "y_up": (0.0, 1.0, 0.0), "z_up": (0.0, 0.0, 1.0)}
CHANS = ("accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z")
OUT_COLS = ("ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps")
QUANTUM_C = 0.0625


@dataclass
class LogTruth:
    white: dict[str, float]  # one-sided density, units/sqrt(Hz) (per-sample sigma = white * sqrt(fs / 2))
    bias_instability: dict[str, float]  # flicker floor B (Allan deviation minimum = 0.664 B), units
    rate_random_walk: dict[str, float]  # K, units/sqrt(s) (Allan deviation K sqrt(tau / 3))
    hysteresis: dict[str, float] = field(default_factory=dict)
    run_offsets: dict[str, list[float]] = field(default_factory=dict)
    power_on_rows: list[int] = field(default_factory=list)


def _temperature_path(rng: np.random.Generator, seconds: int, levels: tuple[float, ...],
                      rate_c_per_min: float) -> np.ndarray:
    """True IMU temperature at 1 Hz: soaks at `levels` in a shuffled up-and-down order joined by
    slow ramps that approach each level exponentially (a chamber's, not a simulator's, shape)."""
    t = np.zeros(seconds)
    cur = 23.0
    i = 0
    order = list(levels) + list(reversed(levels[:-1]))
    k = 0
    while i < seconds:
        target = order[k % len(order)] + float(rng.normal(0.0, 1.0))
        k += 1
        ramp = int(abs(target - cur) / rate_c_per_min * 60.0)
        n = min(ramp + int(rng.uniform(3000, 7000)), seconds - i)
        x = np.arange(n, dtype=float)
        lin = np.clip(x / max(ramp, 1), 0.0, 1.0)
        shape = lin - 0.15 * np.sin(np.pi * lin)  # slow at the end, a little overshoot-free S
        approach = 1.0 - np.exp(-np.maximum(x - ramp, 0.0) / 400.0)
        seg = cur + (target - cur) * (shape * 0.97 + 0.03 * approach)
        t[i:i + n] = seg
        cur = float(seg[-1]) if n else cur
        i += n
    return t


def _flicker(rng: np.random.Generator, n: int, b: float) -> np.ndarray:
    """Flicker (1/f) noise of bias instability B, shaped in the frequency domain (not the simulator's
    sum of Markov processes): one-sided density B^2 / (pi f), whose Allan deviation floor is
    sqrt(2 ln 2 / pi) B = 0.664 B."""
    spectrum = rng.standard_normal(n // 2 + 1) + 1j * rng.standard_normal(n // 2 + 1)
    f = np.fft.rfftfreq(n, d=1.0)
    psd = np.zeros_like(f)
    psd[1:] = b * b / (np.pi * f[1:])
    # A one-sided density S gives a real series of variance sum(S df): scale each bin accordingly.
    spectrum *= np.sqrt(psd * n / 4.0)
    spectrum[0] = 0.0
    return np.fft.irfft(spectrum, n)


def log_like(seed: int, hours: float = 24.0, *, hysteresis: dict[str, float] | None = None,
             travel_c: float = 1.5, run_offsets: dict[str, float] | None = None, continuous: bool = False,
             power_on_column: bool = False, jitter_c: float = 0.03, white: dict[str, float] | None = None,
             bias_instability: dict[str, float] | None = None, rate_random_walk: dict[str, float] | None = None,
             runs_per_orientation: int = 2) -> tuple[pd.DataFrame, LogTruth]:
    """A campaign CSV frame of a motionless 1 Hz log and the truth hidden in it."""
    rng = np.random.default_rng([seed, 0x10611])
    n = int(hours * 3600)
    temp = _temperature_path(rng, n, (-10.0, 5.0, 20.0, 35.0, 50.0), rate_c_per_min=float(rng.uniform(0.3, 0.6)))
    logged = np.round((temp + rng.normal(0.0, jitter_c, n)) / QUANTUM_C) * QUANTUM_C
    white = white or {c: (1.5e-4 if c.startswith("accel") else 0.01) for c in CHANS}
    bias_instability = bias_instability or {c: (5e-5 if c.startswith("accel") else 4e-3) for c in CHANS}
    rate_random_walk = rate_random_walk or {c: (4e-6 if c.startswith("accel") else 2e-4) for c in CHANS}
    truth = LogTruth(white=dict(white), bias_instability=dict(bias_instability),
                     rate_random_walk=dict(rate_random_walk), hysteresis=dict(hysteresis or {}))

    seg = n // len(ORIENTS)
    orient = np.repeat(np.arange(len(ORIENTS)), seg)
    orient = np.concatenate([orient, np.full(n - orient.size, len(ORIENTS) - 1)])
    per_run = max(seg // runs_per_orientation, 1)
    run = 1 + orient * runs_per_orientation + np.minimum((np.arange(n) - orient * seg) // per_run,
                                                         runs_per_orientation - 1)
    t_s = np.arange(n, dtype=float)
    power = np.zeros(n, dtype=np.int64)
    power[0] = 1
    starts = np.flatnonzero(np.diff(run) != 0) + 1
    if not continuous:
        # a real power cycle: 15 minutes off (no rows), then a new run
        for s in starts:
            t_s[s:] += 900.0
        power[starts] = 1
    truth.power_on_rows = np.flatnonzero(power).tolist()

    # Own thermal curves: a bias with a smooth non-polynomial bend, a small scale-factor term.
    x = (temp - 20.0) / 30.0
    force = np.array([UP[ORIENTS[o]] for o in range(len(ORIENTS))])[orient]  # (n, 3)
    err = np.zeros((n, 6))
    coef = rng.uniform(-1.0, 1.0, (6, 4))
    scale_bias = np.array([3e-3, 3e-3, 3e-3, 0.3, 0.3, 0.3])
    for i in range(6):
        err[:, i] = scale_bias[i] * (coef[i, 0] + coef[i, 1] * x + 0.4 * coef[i, 2] * x * x + 0.2 * coef[i, 3] * x ** 3)
    for i in range(3):  # accelerometer scale factor along the vertical axis, with temperature
        err[:, i] += force[:, i] * (1e-3 * coef[i, 2] + 2e-4 * x)
    if hysteresis:
        h = _play(logged_or_true=temp, travel_c=travel_c)
        for c, w in hysteresis.items():
            err[:, CHANS.index(c)] += 0.5 * w * h
    if run_offsets:
        labels = np.unique(run)
        for c, s in run_offsets.items():
            off = rng.normal(0.0, s, labels.size)
            truth.run_offsets[c] = off.tolist()
            err[:, CHANS.index(c)] += off[np.searchsorted(labels, run)]
    for i, c in enumerate(CHANS):
        err[:, i] += rng.standard_normal(n) * white[c] * np.sqrt(0.5)  # 1 Hz rows: sigma = density sqrt(fs / 2)
        err[:, i] += _flicker(rng, n, bias_instability[c])
        err[:, i] += np.cumsum(rng.standard_normal(n)) * rate_random_walk[c]
    frame = pd.DataFrame({
        "t_s": t_s, "run": run, "orientation": [ORIENTS[o] for o in orient], "chamber_c": np.nan,
        "imu_temp_c": logged, "table_rate_dps": 0.0,
    })
    for i, col in enumerate(OUT_COLS):
        frame[col] = err[:, i] + (force[:, i] if i < 3 else 0.0)
    if power_on_column:
        frame["power_on"] = power
    return frame, truth


def _play(logged_or_true: np.ndarray, travel_c: float) -> np.ndarray:
    """Branch state in [-1, 1] of an exponential play operator: +1 after heating by several travels."""
    h = np.empty(logged_or_true.size)
    state = 0.0
    prev = logged_or_true[0]
    for k, v in enumerate(logged_or_true):
        d = v - prev
        prev = v
        state = state + (np.sign(d) - state) * (1.0 - np.exp(-abs(d) / travel_c))
        h[k] = state
    return h
