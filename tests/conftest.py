"""Shared fixtures: a simulated lab world on a virtual clock; logging restored after each test."""

import logging
from collections.abc import Iterator

import pytest

from labrunner.clock import VirtualClock
from labrunner.sims.world import SimLabConfig, SimWorld
from tests import pg_server

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


@pytest.fixture(scope="session")
def pg_cluster() -> Iterator[pg_server.PgServer]:
    """A throwaway PostgreSQL cluster for the session (tests/pg_server.py); skipped without the binaries,
    unless LABRUNNER_REQUIRE_PG=1 (CI), where their absence fails."""
    if pg_server.pg_bin() is None:
        reason = "PostgreSQL 15+ binaries not found (/usr/lib/postgresql/*/bin; apt-get install postgresql)"
        if pg_server.required():
            pytest.fail(f"LABRUNNER_REQUIRE_PG=1 but {reason}")
        pytest.skip(reason)
    server = pg_server.start_server()
    yield server
    server.destroy()


@pytest.fixture
def pg_url(pg_cluster: pg_server.PgServer) -> str:
    """The URL of a fresh, empty PostgreSQL database."""
    return pg_cluster.url(pg_cluster.new_database())


@pytest.fixture(params=["sqlite", "postgresql"])
def store_db(request: pytest.FixtureRequest, tmp_path) -> str:
    """Where a test's store goes, on each backend: a SQLite file's path, or a fresh PostgreSQL database's URL."""
    if request.param == "sqlite":
        return str(tmp_path / "c.db")
    return str(request.getfixturevalue("pg_url"))


@pytest.fixture
def clock():
    return VirtualClock()


@pytest.fixture
def world(clock):
    return SimWorld(SimLabConfig(seed=7), clock.now())
