"""Value types of the commands' options: a value out of range is argparse's usage error (exit 2, naming the
option) before anything runs, instead of an error deep inside numpy, time.sleep or a socket bind."""

from __future__ import annotations

import argparse
import math


def count(text: str) -> int:
    """A whole number >= 0 (seeds, fault counts, how many events)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, not {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, not {text}")
    return value


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds, not {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds, not {text}")
    return value


def seconds(text: str) -> float:
    """A duration >= 0 (how long to wait, or to run)."""
    value = _finite(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, not {text}")
    return value


def interval(text: str) -> float:
    """A refresh interval > 0."""
    value = _finite(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected seconds > 0, not {text}")
    return value


def port(text: str) -> int:
    """A TCP port, 0 (any free one) to 65535."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a port number 0-65535, not {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port number 0-65535, not {text}")
    return value
