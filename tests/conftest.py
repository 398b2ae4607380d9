"""Shared fixtures: a simulated lab world on a virtual clock."""

import pytest

from labrunner.clock import VirtualClock
from labrunner.sims.world import SimLabConfig, SimWorld


@pytest.fixture
def clock():
    return VirtualClock()


@pytest.fixture
def world(clock):
    return SimWorld(SimLabConfig(seed=7), clock.now())
