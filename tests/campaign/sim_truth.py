"""A dry run through the CLI that also records what the simulated world fed the IMU model (the true
sensor temperature, force and rate, chunk by chunk): the truth the lag tests compare the store with."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from labrunner.cli import main
from labrunner.imu.model import ImuInputs
from labrunner.sims.world import SimWorld

FIELDS = ("t_s", "run", "t_on_s", "temp_c", "force_g", "rate_dps")


def dry_run_with_truth(monkeypatch: pytest.MonkeyPatch, proc: Path, sim: Path, db: Path, seed: int) -> ImuInputs:
    """Run `proc` on the simulated lab (`--sim-config sim`) into `db`; returns the IMU model's inputs, joined."""
    fed: list[ImuInputs] = []
    real = SimWorld.imu_inputs

    def recording(self: SimWorld, times: np.ndarray, **kwargs: Any) -> ImuInputs:
        out = real(self, times, **kwargs)  # e.g. history_until (frames made on demand)
        fed.append(out)
        return out

    monkeypatch.setattr(SimWorld, "imu_inputs", recording)
    assert main(["run", str(proc), "--sim", "--sim-config", str(sim), "--seed", str(seed), "--db", str(db),
                 "--quiet"]) == 0
    return ImuInputs(**{f: np.concatenate([np.asarray(getattr(p, f)) for p in fed]) for f in FIELDS})
