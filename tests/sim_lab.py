"""The simulated lab connected and streaming: the fixture the sim-level tests share."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from labrunner.lab import Lab, simulated_lab


@pytest.fixture(name="lab")
def connected_lab() -> Iterator[Lab]:
    """A dry run's lab (in-process lines), every instrument connected and one lab second streamed, so records
    count their frames from a known counter."""
    lab = simulated_lab(max_rate_dps=150.0)
    lab.chamber.connect()
    lab.table.connect()
    lab.imu.connect()
    lab.clock.sleep(1.0)
    yield lab
    lab.close()
