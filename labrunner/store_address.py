"""Where a store lives: a SQLite file (a path, or `sqlite:///path`) or a PostgreSQL database (a SQLAlchemy
URL, `postgresql+psycopg://user@host:port/dbname`).

A URL may carry a password; nothing labrunner prints, logs or stores shows it: `str(address)` is the
URL with the password masked (SQLAlchemy's `render_as_string(hide_password=True)`), and only the engine
sees the real one. Without a password in the URL, libpq takes it from PGPASSWORD or ~/.pgpass.

`is_store` is the one test of "this DATA argument is a store, not a CSV": a URL, or a file with the
SQLite header. Nothing here opens a connection.
"""

from __future__ import annotations

import argparse
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from labrunner.errors import UserError

if TYPE_CHECKING:  # SQLAlchemy is imported when an address is made: every command's start would pay for it
    from sqlalchemy.engine import URL

SQLITE_MAGIC = b"SQLite format 3\x00"
# scheme://... (a Windows drive letter or a relative path has no "://")
_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*://")
# The driver labrunner talks to PostgreSQL with (psycopg 3, a dependency).
PG_DRIVER = "postgresql+psycopg"
SUPPORTED = "a SQLite file (a path or sqlite:///PATH) or PostgreSQL (postgresql+psycopg://USER@HOST:PORT/DBNAME)"


def is_url(text: str | Path) -> bool:
    """Whether a --db/DATA argument is a URL (`scheme://...`), not a path."""
    return isinstance(text, str) and bool(_URL.match(text))


@dataclass(frozen=True)
class StoreAddress:
    """A store's location: `file` for SQLite, else a server database; `url` is what the engine opens."""

    url: URL
    file: Path | None  # the SQLite file; None: a database server

    @property
    def backend(self) -> str:
        """"sqlite" or "postgresql"."""
        return self.url.get_backend_name()

    @property
    def is_server(self) -> bool:
        return self.file is None

    @property
    def masked(self) -> str:
        """The URL with its password hidden (what messages show)."""
        return self.url.render_as_string(hide_password=True)

    @property
    def server(self) -> str:
        """host:port of a server (the socket directory or 'localhost' when the URL names no host)."""
        host = self.url.host or str(self.url.query.get("host") or "localhost")
        return f"{host}:{self.url.port or 5432}"

    def resolve(self) -> StoreAddress:
        """The same store with a file's path made absolute (for provenance); a server's as it is."""
        if self.file is None:
            return self
        return StoreAddress(self.url.set(database=str(self.file.resolve())), self.file.resolve())

    def beside(self, suffix: str) -> Path:
        """A path named after the store: next to a file (`c1.db` -> `c1<suffix>`), or for a server in the
        current directory after its database name (`.../lab` -> `lab<suffix>`)."""
        if self.file is not None:
            return self.file.with_name(self.file.stem + suffix)
        return Path(f"{self.url.database}{suffix}")

    def __str__(self) -> str:
        return str(self.file) if self.file is not None else self.masked


def store_address(db: str | Path | StoreAddress) -> StoreAddress:
    """A --db argument as a store's address: a path (SQLite) or a URL; a URL labrunner cannot use is
    refused with one line (`UserError`) that shows no password."""
    from sqlalchemy.engine import URL, make_url
    from sqlalchemy.exc import ArgumentError

    if isinstance(db, StoreAddress):
        return db
    if not is_url(db):
        path = Path(db)
        return StoreAddress(URL.create("sqlite", database=str(path)), path)
    text = str(db)
    try:
        url = make_url(text)
    except (ArgumentError, ValueError) as exc:
        raise UserError(f"{_mask_text(text)}: not a database URL ({exc}); give {SUPPORTED}") from None
    backend = url.get_backend_name()
    if backend == "sqlite":
        if not url.database or url.database == ":memory:":
            raise UserError(f"{url.render_as_string(hide_password=True)}: a store must be a file "
                            "(sqlite:///PATH)")
        return StoreAddress(url, Path(url.database))
    if backend != "postgresql":
        raise UserError(f"{url.render_as_string(hide_password=True)}: labrunner stores are {SUPPORTED}")
    if url.drivername not in ("postgresql", PG_DRIVER):
        raise UserError(f"{url.render_as_string(hide_password=True)}: the driver {url.get_driver_name()!r} is "
                        f"not the one labrunner uses; write {PG_DRIVER}://...")
    if not url.database:
        raise UserError(f"{url.render_as_string(hide_password=True)}: the URL names no database "
                        f"({PG_DRIVER}://USER@HOST:PORT/DBNAME)")
    return StoreAddress(url.set(drivername=PG_DRIVER), None)


def _mask_text(text: str) -> str:
    """A URL that does not parse, with anything between '//user:' and '@' hidden."""
    return re.sub(r"(://[^/:@]*:)[^@/]*@", r"\1***@", text)


def store_arg(text: str) -> StoreAddress:
    """argparse type of a DB argument: the message of a URL labrunner cannot use, without a traceback."""
    try:
        return store_address(text)
    except UserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def data_arg(text: str) -> str | StoreAddress:
    """argparse type of a DATA argument (a campaign CSV or a store): a URL becomes a store's address, so
    it is printed masked; a path stays as given (its header says what it is, `is_store`)."""
    return store_arg(text) if is_url(text) else text


def is_sqlite_file(path: str | Path) -> bool:
    """Whether the file starts with SQLite's header (only those 16 bytes are read)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(16) == SQLITE_MAGIC
    except OSError:
        return False


def is_store(data: str | Path | StoreAddress) -> bool:
    """Whether analysis data name a store rather than a campaign CSV: a URL, or a SQLite file."""
    if isinstance(data, StoreAddress) or is_url(data):
        return True
    return is_sqlite_file(data)
