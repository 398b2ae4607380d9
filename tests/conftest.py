"""Shared fixtures: a simulated lab world on a virtual clock; logging restored after each test."""

import logging
from collections.abc import Iterator

import pytest

from labrunner.clock import VirtualClock
from labrunner.sims.world import SimLabConfig, SimWorld

_LOGGERS = ("labrunner", "pymodbus", "transitions", "matplotlib", "PIL")


@pytest.fixture(autouse=True)
def _restore_logging() -> Iterator[None]:
    # In-process CLI calls (`main(["-vv", ...])`) configure logging; without this, a later test's
    # simulated-lab threads would keep logging at DEBUG onto the terminal.
    saved = {n: (list(lg.handlers), lg.level, lg.propagate) for n in _LOGGERS for lg in [logging.getLogger(n)]}
    yield
    for name, (handlers, level, propagate) in saved.items():
        lg = logging.getLogger(name)
        lg.handlers[:], lg.level, lg.propagate = handlers, level, propagate


@pytest.fixture
def clock():
    return VirtualClock()


@pytest.fixture
def world(clock):
    return SimWorld(SimLabConfig(seed=7), clock.now())
