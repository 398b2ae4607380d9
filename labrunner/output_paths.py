"""Output paths checked before anything is written (issue 12, item 4): nothing is overwritten silently.

`check_output` is the one check the commands and the Python API make for every file or directory
they write. An output may never be an input of the same command (a store, a CSV, a procedure, a
configuration), nor one of a SQLite store's companion files (`-wal`, `-shm`, `-journal`), not even
with `force`: a campaign store lost to `export w.db --csv w.db` cannot be recovered. An existing file,
or a directory that is not empty, is written only with `force`. `-` (stdout) is never a file.

Paths are compared resolved (symlinks and `..` followed) and, when both exist, with `os.path.samefile`
(hard links, case-insensitive file systems). Nothing here opens a file: closing any descriptor of a
database drops every POSIX lock the process holds on it, SQLite's included, and a process running a
campaign checks its fit directory with the store open (another process could then delete the WAL it
writes). So the caller says which path is the store. A store on a database server (a URL) is no file:
only the other inputs are protected then. This module imports nothing of labrunner but its error class
and `store_address` (both in the base room), so every room may use it.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from labrunner.errors import UserError
from labrunner.store_address import StoreAddress, is_url, store_address

STDOUT = "-"
# Files SQLite keeps beside a database (WAL mode, rollback journal): writing one corrupts the store.
SQLITE_COMPANIONS = ("-wal", "-shm", "-journal")


class OutputPathError(UserError):
    """An output path that would overwrite an input, or an existing output without `force` (exit 2)."""


@dataclass(frozen=True)
class _Protected:
    """A path no output may take, and how a refusal names it."""

    path: Path
    what: str  # "the store w.db", "a companion file of the store w.db", "the input quick.yaml"


def _file_of(given: str | Path | StoreAddress) -> Path | None:
    """The file an input or store names: a path, a SQLite URL's file; None for a server database."""
    if isinstance(given, StoreAddress) or is_url(given):
        try:
            return store_address(given).file
        except UserError:  # a URL no store can have: nothing on disk to protect
            return None
    return Path(given)


def _protected(store: str | Path | StoreAddress | None,
               inputs: Iterable[str | Path | StoreAddress | None]) -> list[_Protected]:
    out: list[_Protected] = []
    for given, role in [(store, "the store"), *((i, "the input") for i in inputs)]:
        if given is None or str(given) == STDOUT:
            continue
        path = _file_of(given)
        if path is None:
            continue
        what = f"{role} {given}"
        # Both the path as given and as resolved: SQLite names its companions after the path it was
        # opened with, and newer versions after the symlink's target. Any input may be a store (fit
        # and diagnose read either), so every input's companions are protected.
        for base in dict.fromkeys((Path(os.path.abspath(path)), path.resolve())):
            out.append(_Protected(base, what))
            out += [_Protected(Path(f"{base}{suffix}"), f"a companion file of {what}") for suffix in SQLITE_COMPANIONS]
    return out


def _same(a: Path, b: Path) -> bool:
    if a == b:
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_output(path: str | Path, *, store: str | Path | StoreAddress | None = None,
                 inputs: Iterable[str | Path | StoreAddress | None] = (),
                 force: bool = False, directory: bool = False, option: str = "output",
                 allow_stdout: bool = False) -> Path | None:
    """Check that writing `path` overwrites nothing it should not; returns it resolved (None: stdout).

    `store` is the database the command reads or writes and `inputs` the other paths it reads (None
    entries are skipped); `directory` says the output is a directory files are written into; `option`
    names it in messages (e.g. `--csv`); with `allow_stdout`, `-` means stdout. Raises
    `OutputPathError` (exit 2) naming the path and the reason.
    """
    if allow_stdout and str(path) == STDOUT:
        return None
    given = Path(path)
    target = given.resolve()
    label = f"{option} {path}"
    protected = _protected(store, inputs)
    for p in protected:
        if _same(target, p.path):
            raise OutputPathError(f"{label} is {p.what}; refusing to overwrite it (choose another path)")
    if directory:
        _check_directory(given, target, label, protected, force)
    else:
        _check_file(given, target, label, force)
    return target


def _check_file(given: Path, target: Path, label: str, force: bool) -> None:
    if target.is_dir():
        raise OutputPathError(f"{label} is a directory; give a file name")
    parent = target.parent
    if not parent.is_dir():
        reason = "is not a directory" if parent.exists() else "does not exist"
        raise OutputPathError(f"cannot write {given}: directory {given.parent} {reason}")
    if target.exists() and not force:
        raise OutputPathError(f"{label} exists; use --force to overwrite it")


def _check_directory(given: Path, target: Path, label: str, protected: list[_Protected], force: bool) -> None:
    if target.exists() and not target.is_dir():
        raise OutputPathError(f"{label} is a file, not a directory")
    ancestor = next(a for a in (target, *target.parents) if a.exists())
    if not ancestor.is_dir():
        raise OutputPathError(f"cannot create {given}: {ancestor} is not a directory")
    if not target.is_dir():
        return  # created by the writer: nothing in it to overwrite
    # The writers put their files straight into the directory, so an input inside it could be hit by
    # name (a CSV called evaluation.csv, a store's -wal); not even --force writes there.
    for p in protected:
        if _same(p.path.parent, target) and p.path.exists():
            raise OutputPathError(f"{label} holds {p.what}; write into another directory")
    if not force and any(target.iterdir()):
        raise OutputPathError(f"{label} is not empty; use --force to write into it")
