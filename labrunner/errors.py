"""Errors a user can act on: the CLI prints their message (no traceback) and exits non-zero."""

from __future__ import annotations


class UserError(Exception):
    """Bad input or a state the user must resolve; the message says where and what."""

    exit_code = 2
