"""The console operator: an Enter typed ahead of a remount prompt confirms nothing; one typed after it does.

Tried on a pseudo-terminal as stdin (what a person at a terminal has) and on a pipe (a script)."""

from __future__ import annotations

import os
import pty
import select
import threading
import time

import pytest

from labrunner.operator import ConsoleOperator, discard_typeahead
from labrunner.yaml_config import ConfigError


class _Prompted:
    """A remount in a thread, its prompt written to a pipe this side reads."""

    def __init__(self, stdin_fd: int) -> None:
        self._r, w = os.pipe()
        self.stream = os.fdopen(w, "w")
        self.error: BaseException | None = None
        self.operator = ConsoleOperator(stream=self.stream, stdin=stdin_fd)
        self.thread = threading.Thread(target=self._remount, daemon=True)
        self.thread.start()

    def _remount(self) -> None:
        try:
            self.operator.remount("y_down", "Mount the IMU with its y axis pointing down.")
        except BaseException as exc:  # handed to the test
            self.error = exc

    def wait_prompt(self, timeout: float = 10.0) -> str:
        seen = b""
        deadline = time.monotonic() + timeout
        while b"Press Enter" not in seen:
            left = deadline - time.monotonic()
            assert left > 0, f"no prompt within {timeout} s: {seen!r}"
            if select.select([self._r], [], [], left)[0]:
                seen += os.read(self._r, 4096)
        return seen.decode()

    def close(self) -> None:
        self.stream.close()
        os.close(self._r)


def _readable(fd: int, timeout: float = 5.0) -> None:
    assert select.select([fd], [], [], timeout)[0], "the typed-ahead input never reached the reader"


def test_typeahead_on_a_terminal_does_not_confirm_a_remount():
    master, slave = pty.openpty()
    try:
        os.write(master, b"\n")  # a stray Enter, typed while the chamber was still on its way
        _readable(slave)  # it waits in the terminal's input queue
        prompted = _Prompted(slave)
        text = prompted.wait_prompt()
        assert "OPERATOR: Mount the IMU with its y axis pointing down." in text
        prompted.thread.join(1.0)
        assert prompted.thread.is_alive(), "the Enter typed ahead confirmed the remount"
        os.write(master, b"\n")  # the operator's answer, after the prompt
        prompted.thread.join(5.0)
        assert not prompted.thread.is_alive() and prompted.error is None
        prompted.close()
    finally:
        os.close(master)
        os.close(slave)


def test_typeahead_on_a_pipe_is_discarded_too_and_one_answer_confirms_one_prompt():
    r, w = os.pipe()
    try:
        os.write(w, b"\n\nyes\n")  # several lines waiting before the first prompt
        prompted = _Prompted(r)
        prompted.wait_prompt()
        prompted.thread.join(1.0)
        assert prompted.thread.is_alive()
        os.write(w, b"\n\n")  # answered once, with an extra Enter that must not confirm the next prompt
        prompted.thread.join(5.0)
        assert not prompted.thread.is_alive() and prompted.error is None
        prompted.close()
        second = _Prompted(r)
        second.wait_prompt()
        second.thread.join(1.0)
        assert second.thread.is_alive(), "the second Enter of the first answer confirmed the next prompt"
        os.write(w, b"\n")
        second.thread.join(5.0)
        assert not second.thread.is_alive() and second.error is None
        second.close()
    finally:
        os.close(r)
        os.close(w)


def test_discard_counts_what_a_pipe_held_and_returns_at_once_when_empty():
    r, w = os.pipe()
    try:
        assert discard_typeahead(r) == 0
        os.write(w, b"abc\n")
        assert discard_typeahead(r) == 4
        assert not select.select([r], [], [], 0)[0]
    finally:
        os.close(r)
        os.close(w)


def test_a_closed_stdin_is_a_clear_error_not_a_hang():
    r, w = os.pipe()
    os.close(w)
    try:
        prompted = _Prompted(r)
        prompted.wait_prompt()
        prompted.thread.join(5.0)
        assert isinstance(prompted.error, ConfigError)
        assert "operator prompt for y_down: no terminal to acknowledge it (stdin closed)" in str(prompted.error)
        prompted.close()
    finally:
        os.close(r)


@pytest.mark.parametrize("stdin", [None, "closed"])
def test_no_stdin_at_all_is_the_same_clear_error(monkeypatch, stdin):
    import io
    import sys

    if stdin is None:
        monkeypatch.setattr(sys, "stdin", None)
    else:
        closed = io.StringIO()
        closed.close()
        monkeypatch.setattr(sys, "stdin", closed)
    with pytest.raises(ConfigError, match="no terminal to acknowledge it"):
        ConsoleOperator(stream=io.StringIO()).remount("x_up", "Mount x up")
