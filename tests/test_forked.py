"""Independent parts in forked children (`labrunner.forked`): the results of running them here, in order;
a child that fails or dies has its part run here, and a part's own error reaches the caller."""

from __future__ import annotations

import os
import signal

import pytest

from labrunner.errors import UserError
from labrunner.forked import ENV, balanced_groups, can_fork, configured_processes, fork_map

needs_fork = pytest.mark.skipif(not can_fork(), reason="no fork here")


def _pid_and_square(x: int) -> tuple[int, int]:
    return os.getpid(), x * x


@needs_fork
def test_parts_run_in_children_and_come_back_in_order() -> None:
    got = fork_map(_pid_and_square, [1, 2, 3, 4], processes=4)
    assert [v for _, v in got] == [1, 4, 9, 16]
    pids = [p for p, _ in got]
    assert pids[0] == os.getpid() and len(set(pids)) == 4  # the first here, each other in its own child
    for pid in pids[1:]:  # every child reaped
        with pytest.raises(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)


def test_one_process_runs_everything_here(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV, "1")
    assert configured_processes() == 1
    got = fork_map(_pid_and_square, [5, 6])
    assert got == [(os.getpid(), 25), (os.getpid(), 36)]


@pytest.mark.parametrize("raw", ["0", "two", "-3"])
def test_a_bad_setting_is_named(monkeypatch: pytest.MonkeyPatch, raw: str) -> None:
    monkeypatch.setenv(ENV, raw)
    with pytest.raises(UserError, match=ENV):
        configured_processes()


def _fails_in_children(parent: int) -> int:
    if os.getpid() != parent:
        raise RuntimeError("only in a child")
    return 7


def _dies_in_children(parent: int) -> int:
    if os.getpid() != parent:
        os.kill(os.getpid(), signal.SIGKILL)
    return 8


def _fails_everywhere(_: int) -> int:
    raise ValueError("part 2 cannot be done")


@needs_fork
def test_a_part_that_fails_or_dies_in_its_child_runs_here() -> None:
    me = os.getpid()
    assert fork_map(_fails_in_children, [me, me], processes=2) == [7, 7]
    assert fork_map(_dies_in_children, [me, me], processes=2) == [8, 8]


@needs_fork
def test_a_parts_own_error_reaches_the_caller() -> None:
    with pytest.raises(ValueError, match="part 2 cannot be done"):
        fork_map(_fails_everywhere, [1, 2], processes=2)


def test_balanced_groups() -> None:
    assert balanced_groups([1.5, 1, 1, 1, 1], 2) == [[0, 3], [1, 2, 4]]  # 2.5 and 3
    groups = balanced_groups([3, 1, 1, 1], 2)
    assert sorted(groups) == [[0], [1, 2, 3]]
    assert balanced_groups([1, 1], 5) == [[0], [1]]  # no empty group
    assert sorted(i for g in balanced_groups([0.2] * 7, 3) for i in g) == list(range(7))
