"""The campaign store: SQLite or PostgreSQL through SQLAlchemy Core (`store_address`: a path or a URL).

Tables: campaigns (procedure text and hash, lab configuration, software version,
status), steps (the planned record steps and their status), sample_blocks (one row
per record step, the samples as typed little-endian blobs: counter offsets int32,
accel/gyro/temp float32, plus the chamber and table readings taken while
recording; also 'monitor' blocks of 1 s means while ramping and soaking), events
(every state transition, fault and recovery, with its time), fits, and control
(pause/abort requests from another process).

A record step is written with its step status and its event in one transaction,
so after any crash a step is either complete or absent; a partial unique index
makes a second copy of a step impossible (partial on both backends). On SQLite, WAL
and synchronous=NORMAL on every connection. Readers return pandas frames.

A database that cannot be read or written (disk full, lost connection, read-only
file, a server gone) raises `StoreError`, one line naming the database and what it said, so
the sequencer can tell a store failure from an instrument's and bring the lab to
its safe state before it touches the store again.
"""

from __future__ import annotations

import getpass
import json
import logging
import os
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import (
    Column,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    String,
    Table,
    Text,
    bindparam,
    case,
    create_engine,
    event,
    func,
    insert,
    inspect,
    select,
    text,
    update,
)
from sqlalchemy.engine import Connection, CursorResult, Engine
from sqlalchemy.exc import DatabaseError, IntegrityError, OperationalError

from labrunner.domain import ACCEL_COLUMNS, GYRO_COLUMNS, ORIENTATIONS
from labrunner.domain import CSV_COLUMNS as COLUMNS
from labrunner.errors import UserError
from labrunner.store_address import StoreAddress, store_address
from labrunner.version import __version__

if TYPE_CHECKING:  # pandas is imported where frames are built: `labrunner list`/`status` do not load it
    import pandas as pd

log = logging.getLogger(__name__)

# What a database that cannot be used raises (SQLite: SQLITE_FULL, SQLITE_READONLY, SQLITE_IOERR, ...).
# IntegrityError is a DatabaseError too but not a failing store: a write the schema refuses (a step
# stored twice) is the writer's error and stays one.
_STORE_FAILURES = (OperationalError, DatabaseError, OSError)


class StoreError(UserError):
    """The database could not be read or written; the message names it and the cause."""

    exit_code = 1  # a failed run, not bad input

    def __init__(self, path: StoreAddress, doing: str, cause: BaseException) -> None:
        self.path = path
        self.cause = _cause(cause)
        super().__init__(f"cannot {doing} the database {path}: {self.cause}")


def _cause(exc: BaseException) -> str:
    """The DBAPI error in one line, without SQLAlchemy's SQL and parameters (libpq's messages span
    lines: "connection failed: ...\\n\\tIs the server running ...?")."""
    orig = getattr(exc, "orig", None)
    return " ".join(str(orig if orig is not None else exc).split()) or type(exc).__name__


class StoreUnavailable(StoreError):
    """A database server that cannot be reached or refuses the login (one line, no password)."""

    def __init__(self, path: StoreAddress, message: str, cause: BaseException) -> None:
        self.path = path
        self.cause = _cause(cause)
        UserError.__init__(self, message)


# What SQLite says when a page it reads is damaged.
_DAMAGED = ("database disk image is malformed", "file is not a database")
# What SQLite says of a file that is not a labrunner store (another file, an empty or another database).
_NOT_A_STORE = ("file is not a database", "no such table", "does not exist")  # PG: relation "..." does not exist

# 2: the campaign lease (campaigns.lease_token, lease_wall). A version-1 store is migrated when opened.
SCHEMA_VERSION = 2
# Columns `samples_frame(with_steps=True)` adds to the campaign CSV columns.
STEP_COLUMNS = ("kind", "state", "step_idx", "setpoint_c", "rate_cmd_dps")
metadata = MetaData()

campaigns = Table(
    "campaigns", metadata,
    Column("id", Integer, primary_key=True),
    Column("name", String, nullable=False),
    Column("procedure_path", String),
    Column("procedure_text", Text, nullable=False),
    Column("procedure_sha256", String, nullable=False),
    Column("lab_config", Text, nullable=False),  # JSON
    Column("mode", String, nullable=False),  # "sim" or "lab"
    Column("sim_config", Text),  # JSON (seed, faults) for dry runs
    Column("software_version", String, nullable=False),
    Column("status", String, nullable=False),  # running, paused, aborted, failed, done
    Column("created_wall", Float, nullable=False),
    Column("updated_wall", Float, nullable=False),
    Column("clock_t0", Float, nullable=False),  # clock time of campaign time zero
    Column("clock_last", Float, nullable=False),  # last clock time seen (a resumed dry run continues from here)
    Column("pid", Integer),
    Column("host", String),
    Column("n_steps", Integer, nullable=False),
    # The campaign lease: one writer per campaign. The holder's token (NULL: free), and the wall time
    # of its last renewal (the heartbeat); pid and host above name the holder.
    Column("lease_token", String),
    Column("lease_wall", Float),
)

steps = Table(
    "steps", metadata,
    Column("campaign_id", Integer, ForeignKey("campaigns.id"), primary_key=True),
    Column("idx", Integer, primary_key=True),
    Column("orientation", String, nullable=False),
    Column("temperature_c", Float, nullable=False),
    Column("rate_dps", Float, nullable=False),
    Column("status", String, nullable=False),  # planned, done
    Column("run", Integer),
    Column("attempts", Integer, nullable=False, default=0),
    Column("t_start", Float),
    Column("t_end", Float),
    Column("n_samples", Integer),
    Column("dropped", Integer),
    Column("corrupt", Integer),
    Column("imu_temp_c", Float),
    Column("chamber_c", Float),
)

sample_blocks = Table(
    "sample_blocks", metadata,
    Column("id", Integer, primary_key=True),
    Column("campaign_id", Integer, ForeignKey("campaigns.id"), nullable=False),
    Column("kind", String, nullable=False),  # record, monitor
    Column("step_idx", Integer),
    Column("run", Integer, nullable=False),
    Column("orientation", String, nullable=False),
    Column("t0_s", Float, nullable=False),  # campaign time of the first sample
    Column("rate_hz", Float, nullable=False),
    Column("n", Integer, nullable=False),
    Column("counter", LargeBinary, nullable=False),  # int32 offsets from the first sample's counter
    # Samples as the IMU sent them: int16 counts with their LSB sizes (lossless), or float32 when
    # they are not whole counts (monitor means, an IMU that sends floats).
    Column("encoding", String, nullable=False),  # "i16" or "f32"
    Column("accel_lsb", Float),
    Column("gyro_lsb", Float),
    Column("temp_lsb", Float),
    Column("accel_g", LargeBinary, nullable=False),  # (n, 3)
    Column("gyro_dps", LargeBinary, nullable=False),  # (n, 3)
    Column("temp_c", LargeBinary, nullable=False),  # (n,)
    Column("chamber", LargeBinary, nullable=False),  # float64 pairs (t_s, deg C) read while recording
    Column("table", LargeBinary, nullable=False),  # float64 pairs (t_s, deg/s)
    Index("one_record_per_step", "campaign_id", "step_idx", unique=True, sqlite_where=text("kind = 'record'"),
          postgresql_where=text("kind = 'record'")),
    Index("blocks_by_time", "campaign_id", "t0_s"),
)

events = Table(
    "events", metadata,
    Column("id", Integer, primary_key=True),
    Column("campaign_id", Integer, ForeignKey("campaigns.id"), nullable=False),
    Column("t_s", Float, nullable=False),  # campaign time
    Column("wall", Float, nullable=False),
    Column("kind", String, nullable=False),  # transition, fault, recovery, warning, operator, info
    Column("state", String),
    Column("step_idx", Integer),
    Column("message", Text, nullable=False),
    Column("detail", Text),  # JSON
    Index("events_by_campaign", "campaign_id", "id"),
)

fits = Table(
    "fits", metadata,
    Column("id", Integer, primary_key=True),
    Column("campaign_id", Integer, ForeignKey("campaigns.id"), nullable=False),
    Column("created_wall", Float, nullable=False),
    Column("software_version", String, nullable=False),
    Column("provenance", Text, nullable=False),  # JSON: data range, rows, source
    Column("result", Text, nullable=False),  # JSON
)

control = Table(
    "control", metadata,
    Column("campaign_id", Integer, ForeignKey("campaigns.id"), primary_key=True),
    Column("request", String),  # pause, abort
    Column("requested_wall", Float),
)

meta = Table(
    "labrunner_meta", metadata,
    Column("key", String, primary_key=True),
    Column("value", String, nullable=False),
)

# The statements a running campaign executes thousands of times (a paper dry run: ~50 000), built once:
# SQLAlchemy then finds each one's compiled form in its cache by the statement's own key instead of
# building and hashing a new expression tree per call (~5x the cost of the execution itself on SQLite).
# The SET columns of the UPDATEs come from the parameters given (bound names in WHERE start with "w_",
# apart from the column names).
_RENEW = update(campaigns).where(campaigns.c.id == bindparam("w_id"), campaigns.c.lease_token == bindparam("w_token"))
_UPDATE_CAMPAIGN = update(campaigns).where(campaigns.c.id == bindparam("w_id"))
_UPDATE_STEP = update(steps).where(steps.c.campaign_id == bindparam("w_campaign"), steps.c.idx == bindparam("w_idx"))
_ATTEMPT = _UPDATE_STEP.values(attempts=steps.c.attempts + 1)
_INSERT_BLOCK = insert(sample_blocks)
_INSERT_EVENT = insert(events)
# The first step not yet done at or after a known one (steps only ever become done): the primary key's
# order, stopping at the first match, instead of a scan of every done step per call.
_NEXT_STEP = (select(steps.c.idx)
              .where(steps.c.campaign_id == bindparam("w_campaign"), steps.c.idx >= bindparam("w_from"),
                     steps.c.status != "done").order_by(steps.c.idx).limit(1))
_PENDING = select(control.c.request).where(control.c.campaign_id == bindparam("w_campaign"))
# On SQLite, each of them compiled once more, to its SQL text and the order of its values (by the keys of
# the parameters it is given): statement -> (SQL, for each value the parameter's name or a constant).
_PREPARED: dict[tuple[int, tuple[str, ...]], tuple[str, tuple[tuple[bool, Any], ...]] | None] = {}


def _hot(conn: Connection, stmt: Any, params: dict[str, Any]) -> CursorResult[Any]:
    """Run one of the hot statements above. On SQLite as its SQL text with the values in order through
    `exec_driver_sql`: the engine's events fire and DBAPI errors are wrapped as for any statement, but the
    per-call compiled-cache lookup, parameter processing and execution context of `execute` (most of a small
    write's CPU there) are saved; the hot statements' values need no conversion for SQLite's driver (int,
    float, str, bytes, None), so the rows are the same. Other databases: `execute`."""
    if conn.dialect.name != "sqlite":
        return conn.execute(stmt, params)
    key = (id(stmt), tuple(params))
    if key not in _PREPARED:
        _PREPARED[key] = _prepare(conn, stmt, list(params))
    prepared = _PREPARED[key]
    if prepared is None:
        return conn.execute(stmt, params)
    sql, order = prepared
    return conn.exec_driver_sql(sql, tuple(params[v] if named else v for named, v in order))


def _prepare(conn: Connection, stmt: Any, keys: list[str]) -> tuple[str, tuple[tuple[bool, Any], ...]] | None:
    """A statement's SQL for this connection's (positional) dialect and where each value comes from: a
    parameter by name, or a constant of the statement (`!= 'done'`, `+ 1`); None when that cannot be said
    plainly (escaped bind names, a named paramstyle): then it runs through `execute`."""
    compiled = stmt.compile(dialect=conn.dialect, column_keys=keys)
    names = compiled.positiontup
    if not compiled.positional or names is None or compiled.escaped_bind_names:
        return None
    order = tuple((True, name) if name in keys else (False, compiled.binds[name].effective_value) for name in names)
    return compiled.string, order



@dataclass
class SampleBlock:
    """Samples of one record step (or one monitor stretch) with what was read beside them."""

    kind: str  # "record" or "monitor"
    step_idx: int | None
    run: int
    orientation: str
    t0_s: float
    rate_hz: float
    counter: np.ndarray  # (n,) int
    accel_g: np.ndarray  # (n, 3)
    gyro_dps: np.ndarray  # (n, 3)
    temp_c: np.ndarray  # (n,)
    chamber: np.ndarray  # (k, 2): t_s, deg C
    table: np.ndarray  # (m, 2): t_s, deg/s
    lsb: tuple[float, float, float] | None = None  # accel, gyro, temp LSB: values are whole counts

    def __len__(self) -> int:
        return int(self.counter.size)

    def times(self) -> np.ndarray:
        return self.t0_s + (self.counter - self.counter[0]) / self.rate_hz if len(self) else np.zeros(0)


def _f32(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype="<f4").tobytes()


def _encode(values: np.ndarray, lsb: float | None) -> bytes:
    if lsb is None:
        return _f32(values)
    return np.ascontiguousarray(np.rint(np.asarray(values) / lsb), dtype="<i2").tobytes()


def _decode(raw: bytes, encoding: str, lsb: float | None, shape: tuple[int, ...]) -> np.ndarray:
    if encoding == "i16":
        return np.frombuffer(raw, dtype="<i2").reshape(shape) * lsb
    return np.frombuffer(raw, dtype="<f4").reshape(shape).astype(float)


def _f64(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype="<f8").tobytes()


def _checked_row(row: Any, path: StoreAddress) -> tuple[float, float, float] | None:
    """A stored block row whose blobs hold what the row says (the LSB sizes of an int16 block, None for
    float32), or `StoreDamage` naming its campaign, step and the blob that does not (a short or
    garbled blob would otherwise be a reshape error)."""
    n, enc = row["n"], row["encoding"]

    def damaged(what: str) -> StoreDamage:  # the place named only when there is damage to name
        where = (f"{path}: campaign {row['campaign_id']}, table sample_blocks, "
                 + (f"step {row['step_idx']}" if row["step_idx"] is not None else f"{row['kind']} block at "
                    f"t={row['t0_s']:.1f} s") + f" (block {row['id']})")
        return StoreDamage(f"{where}: {what}; the store is damaged")

    if enc not in ("i16", "f32") or not isinstance(n, int) or n < 0:
        raise damaged(f"encoding {enc!r} with {n!r} samples is not one labrunner writes")
    width = 2 if enc == "i16" else 4
    expected = (("counter", 4 * n), ("accel_g", 3 * n * width), ("gyro_dps", 3 * n * width), ("temp_c", n * width))
    for column, size in expected:
        raw = row[column]
        if not isinstance(raw, bytes) or len(raw) != size:
            got = len(raw) if isinstance(raw, bytes) else type(raw).__name__
            raise damaged(f"column {column} holds {got} bytes, {n} samples need {size}")
    for column in ("chamber", "table"):
        raw = row[column]
        if not isinstance(raw, bytes) or len(raw) % 16:
            raise damaged(f"column {column} is not (time, value) float64 pairs")
    if enc != "i16":
        return None
    la, lg, lt = row["accel_lsb"], row["gyro_lsb"], row["temp_lsb"]
    if not (isinstance(la, float) and la > 0 and isinstance(lg, float) and lg > 0 and isinstance(lt, float)
            and lt > 0):
        raise damaged("int16 samples without their LSB sizes")
    return (la, lg, lt)


def _block_from_row(row: Any, path: StoreAddress) -> SampleBlock:
    """A stored sample block decoded (`StoreDamage` if its blobs do not hold what its row says)."""
    lsb = _checked_row(row, path)
    n, enc = row["n"], row["encoding"]
    return SampleBlock(
        kind=row["kind"], step_idx=row["step_idx"], run=row["run"], orientation=row["orientation"],
        t0_s=row["t0_s"], rate_hz=row["rate_hz"],
        counter=np.frombuffer(row["counter"], dtype="<i4").astype(np.int64),
        accel_g=_decode(row["accel_g"], enc, row["accel_lsb"], (n, 3)),
        gyro_dps=_decode(row["gyro_dps"], enc, row["gyro_lsb"], (n, 3)),
        temp_c=_decode(row["temp_c"], enc, row["temp_lsb"], (n,)),
        chamber=np.frombuffer(row["chamber"], dtype="<f8").reshape(-1, 2),
        table=np.frombuffer(row["table"], dtype="<f8").reshape(-1, 2),
        lsb=lsb,
    )


@dataclass(frozen=True)
class StoredBlock:
    """A stored block row, checked, its samples decoded a slice at a time (`Store.stored_blocks`): what
    a reader of long blocks uses instead of `SampleBlock` so that its memory follows the slice it works
    on, not the block (a 10x longer record step holds 10x the samples). Values as `SampleBlock`'s,
    bit for bit."""

    kind: str
    step_idx: int | None
    run: int
    orientation: str
    t0_s: float
    rate_hz: float
    lsb: tuple[float, float, float] | None  # int16 counts of these LSB sizes (accel, gyro, temp); None: float32
    chamber: np.ndarray  # (k, 2): t_s, deg C (a view of the blob)
    table: np.ndarray  # (m, 2): t_s, deg/s
    _row: dict[str, Any]

    def __len__(self) -> int:
        return int(self._row["n"])

    def times(self, lo: int, hi: int) -> np.ndarray:
        """`SampleBlock.times()[lo:hi]`."""
        counter = np.frombuffer(self._row["counter"], dtype="<i4")
        return self.t0_s + (counter[lo:hi].astype(np.int64) - np.int64(counter[0])) / self.rate_hz

    def counts(self, column: str, lo: int, hi: int) -> np.ndarray:
        """Rows lo:hi of an int16 block's stored counts of `column` (accel_g, gyro_dps: (rows, 3); temp_c:
        (rows,)), a view of the blob."""
        if self.lsb is None:
            raise ValueError("a float32 block holds no counts")
        return self._stored(column, "<i2")[lo:hi]

    def values(self, column: str, lo: int, hi: int) -> np.ndarray:
        """Rows lo:hi of `column` decoded to float64, as `SampleBlock`'s."""
        if self.lsb is None:
            return self._stored(column, "<f4")[lo:hi].astype(float)
        return self.counts(column, lo, hi) * self.lsb[("accel_g", "gyro_dps", "temp_c").index(column)]

    def _stored(self, column: str, dtype: str) -> np.ndarray:
        raw = np.frombuffer(self._row[column], dtype=dtype)
        return raw if column == "temp_c" else raw.reshape(-1, 3)


def _stored_block(row: dict[str, Any], path: StoreAddress) -> StoredBlock:
    lsb = _checked_row(row, path)
    return StoredBlock(kind=row["kind"], step_idx=row["step_idx"], run=row["run"], orientation=row["orientation"],
                       t0_s=row["t0_s"], rate_hz=row["rate_hz"], lsb=lsb,
                       chamber=np.frombuffer(row["chamber"], dtype="<f8").reshape(-1, 2),
                       table=np.frombuffer(row["table"], dtype="<f8").reshape(-1, 2), _row=row)


def _end_time(row: Any) -> float:
    """Campaign time of a checked block row's last sample, as the frame's time column computes it."""
    counter = np.frombuffer(row["counter"], dtype="<i4")
    return float(np.add(np.divide(np.subtract(counter[-1:], counter[0], dtype=np.float64), row["rate_hz"]),
                        row["t0_s"])[0])


class _BlockColumns:
    """Stored blocks' samples in the campaign CSV columns, filled block by block into columns
    preallocated to `total` rows: the one block -> columns conversion (`Store.samples_frame` and
    `Store.frames`). No per-row Python objects (orientation is one code per block), no concatenation.

    The IMU channels (accelerometer, gyro, temperature) are kept as the stored int16 counts when
    `counts` and every block holds counts of the same LSB sizes, else float64. `lsb`: those sizes,
    decided beforehand (`Store.frames`: every chunk alike), or None to find them from the blocks
    (the first block's; a block of other sizes or of floats turns the columns into float64, the
    values the decoding gives). `labels` are the orientation categories, the six first; a new label
    is appended to the list given (`Store.frames` shares it between chunks)."""

    _IMU = (*ACCEL_COLUMNS, *GYRO_COLUMNS, "imu_temp_c")

    def __init__(self, total: int, lsb: tuple[float, float, float] | None, labels: list[str], path: StoreAddress,
                 *, counts: bool, with_steps: bool = False) -> None:
        self.total, self.labels, self.path, self.with_steps = total, labels, path, with_steps
        self.cols: dict[str, np.ndarray] = {c: np.empty(total) for c in ("t_s", "chamber_c", "table_rate_dps")}
        self.lsb: tuple[float, float, float] | None = None
        self.undecided = counts and lsb is None  # counts wanted, LSB sizes from the first block
        if counts and lsb is not None:
            self._counts(lsb)
        elif not counts:
            self._floats()
        self.run = np.empty(total, dtype=np.int64)
        self.codes = np.empty(total, dtype=np.int8)
        self.step_idx = np.empty(total if with_steps else 0)
        self.kind = np.empty(total if with_steps else 0, dtype=object)
        self.at = 0
        self.first_t = np.inf  # the earliest block start and latest block end filled (the time range of
        self.last_t = -np.inf  # rows whose time ascends within each block: a validated campaign's)

    def _counts(self, lsb: tuple[float, float, float]) -> None:
        # The blobs' layout: a block's (n, 3) counts are one copy, the columns views.
        self.lsb = lsb
        self.accel_counts = np.empty((self.total, 3), dtype=np.int16)
        self.gyro_counts = np.empty((self.total, 3), dtype=np.int16)
        self.cols.update({c: self.accel_counts[:, j] for j, c in enumerate(ACCEL_COLUMNS)}
                         | {c: self.gyro_counts[:, j] for j, c in enumerate(GYRO_COLUMNS)}
                         | {"imu_temp_c": np.empty(self.total, dtype=np.int16)})

    def _floats(self) -> None:
        """The IMU columns as float64 from here on: the counts filled so far converted (counts x LSB in
        float64, what `_decode` gives)."""
        lsb, self.lsb = self.lsb, None
        for j, c in enumerate(self._IMU):
            values = np.empty(self.total)
            if lsb is not None:
                np.multiply(self.cols[c][:self.at], lsb[0 if j < 3 else 1 if j < 6 else 2], out=values[:self.at],
                            dtype=np.float64)
            self.cols[c] = values

    def add(self, row: Any) -> bool:
        """Fill the next rows from a stored block row (`StoreDamage` if its blobs do not hold what it
        says); False when it does not fit what was counted (a block written since: not read)."""
        block_lsb = _checked_row(row, self.path)
        n = int(row["n"])
        if self.undecided:  # an empty block's encoding counts too: it is one of the campaign's blocks
            self.undecided = False
            if block_lsb is None:
                self._floats()
            else:
                self._counts(block_lsb)
        at, cols = self.at, self.cols
        if at + n > self.total:  # rows written since the count: read what was counted
            return False
        if self.lsb is not None and block_lsb != self.lsb:
            self._floats()  # counts of other LSB sizes, or floats: the columns are decoded from here on
        if n == 0:
            return True
        sl = slice(at, at + n)
        # SampleBlock.times() computed in place: t0 + (counter - counter[0]) / rate (whole numbers below
        # 2**31 subtract exactly in float64)
        counter = np.frombuffer(row["counter"], dtype="<i4")
        t = cols["t_s"][sl]
        np.subtract(counter, counter[0], out=t, dtype=np.float64)
        np.divide(t, row["rate_hz"], out=t)
        np.add(t, row["t0_s"], out=t)
        self.first_t = min(self.first_t, float(t[0]))
        self.last_t = max(self.last_t, float(t[-1]))
        orientation = row["orientation"]
        if orientation not in self.labels:
            self.labels.append(orientation)
        self.codes[sl] = self.labels.index(orientation)
        self.run[sl] = row["run"]
        interp_readings(t, np.frombuffer(row["chamber"], dtype="<f8").reshape(-1, 2), out=cols["chamber_c"][sl])
        interp_readings(t, np.frombuffer(row["table"], dtype="<f8").reshape(-1, 2), default=0.0,
                        out=cols["table_rate_dps"][sl])
        enc, la, lg, lt = row["encoding"], row["accel_lsb"], row["gyro_lsb"], row["temp_lsb"]
        if self.lsb is not None:  # the stored counts as they are: one encoding and LSB
            self.accel_counts[sl] = np.frombuffer(row["accel_g"], dtype="<i2").reshape(n, 3)
            self.gyro_counts[sl] = np.frombuffer(row["gyro_dps"], dtype="<i2").reshape(n, 3)
            cols["imu_temp_c"][sl] = np.frombuffer(row["temp_c"], dtype="<i2")
        else:
            accel = _decode(row["accel_g"], enc, la, (n, 3))
            gyro = _decode(row["gyro_dps"], enc, lg, (n, 3))
            cols["imu_temp_c"][sl] = _decode(row["temp_c"], enc, lt, (n,))
            for j, c in enumerate(ACCEL_COLUMNS):
                cols[c][sl] = accel[:, j]
            for j, c in enumerate(GYRO_COLUMNS):
                cols[c][sl] = gyro[:, j]
        if self.with_steps:
            self.step_idx[sl] = np.nan if row["step_idx"] is None else row["step_idx"]
            self.kind[sl] = row["kind"]
        self.at = at + n
        return True

    def frame(self, categorical: bool, *, sort: bool, start: int = 0) -> pd.DataFrame:
        """The rows filled, as a frame (see `Store.samples_frame`); `sort`: stably by time (monitor
        rows among the records; rows already in time order are left as they are). Its RangeIndex
        starts at `start`."""
        import pandas as pd

        if self.undecided:  # no block at all
            self._floats()
        at, cols = self.at, self.cols
        orientation_col: Any = pd.Categorical.from_codes(self.codes[:at], categories=list(self.labels))
        if not categorical:
            orientation_col = np.asarray(self.labels, dtype=object)[self.codes[:at]]
        data: dict[str, Any] = {c: (self.run[:at] if c == "run" else orientation_col if c == "orientation"
                                    else cols[c][:at]) for c in COLUMNS}
        if self.lsb is not None:
            from labrunner.data_source import ScaledFloatArray

            la, lg, lt = self.lsb
            scale = dict.fromkeys(ACCEL_COLUMNS, la) | dict.fromkeys(GYRO_COLUMNS, lg) | {"imu_temp_c": lt}
            data.update({c: ScaledFloatArray(cols[c][:at], s) for c, s in scale.items()})
        if self.with_steps:
            data.update(kind=self.kind[:at], state=np.full(at, None, dtype=object), step_idx=self.step_idx[:at])
        frame = pd.DataFrame(data, copy=False)
        t = cols["t_s"][:at]
        if sort and not bool((t[1:] >= t[:-1]).all()):  # (a stable sort of sorted rows changes nothing)
            frame = frame.sort_values("t_s", kind="stable").reset_index(drop=True)
        if start:
            frame.index = pd.RangeIndex(start, start + len(frame))
        return frame


def _json(value: str | None, path: StoreAddress, campaign_id: int, table: str, column: str) -> Any:
    """A stored JSON column decoded, or `StoreDamage` naming the campaign, table and column."""
    if value is None:
        return None
    try:
        return json.loads(value)
    except (ValueError, TypeError) as exc:
        raise StoreDamage(f"{path}: campaign {campaign_id}, table {table}: column {column} is not JSON ({exc}); "
                          "the store is damaged") from None


@dataclass
class CampaignInfo:
    id: int
    name: str
    status: str
    mode: str
    procedure_text: str
    procedure_path: str | None
    procedure_sha256: str
    lab_config: dict[str, Any]
    sim_config: dict[str, Any] | None
    software_version: str
    created_wall: float
    updated_wall: float
    clock_t0: float
    clock_last: float
    pid: int | None
    host: str | None
    n_steps: int
    lease_token: str | None = None
    lease_wall: float | None = None


@dataclass(frozen=True)
class LeaseHolder:
    """Who holds a campaign's lease, as read inside the transaction that may take it."""

    campaign_id: int
    token: str | None  # None: the lease is free
    pid: int | None
    host: str | None
    heartbeat_wall: float | None  # wall time of the holder's last renewal


class LeaseLost(StoreError):
    """This process's lease on a campaign was taken over: it must not write to the campaign again."""

    def __init__(self, path: StoreAddress, campaign_id: int) -> None:
        self.path = path
        self.cause = f"the lease on campaign {campaign_id} was taken over by another process"
        UserError.__init__(self, f"{path}: {self.cause}; this process stops writing to it")


class StoreDamage(UserError):
    """The database is damaged; the message says where (campaign, table, step) and what."""


def _inserted_id(result: CursorResult[Any]) -> int:
    """The primary key of a single-row insert (every table here has an integer autoincrement key)."""
    key = result.inserted_primary_key
    if key is None:  # pragma: no cover - SQLite reports the rowid of every single-row insert
        raise RuntimeError("the insert reported no primary key")
    return int(key[0])


def _on_connect(dbapi_conn: Any, _record: Any) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute("PRAGMA foreign_keys=ON")
    cur.execute("PRAGMA busy_timeout=10000")
    cur.close()


def _server_refusal(address: StoreAddress, exc: BaseException) -> UserError | None:
    """What a PostgreSQL server's refusal to connect means, in one line naming host:port and the user
    (never the password); None when it is not a refusal to connect (or the store is a file)."""
    if not address.is_server:
        return None
    msg = _cause(exc)
    low = msg.lower()
    url, at = address.url, address.server
    user = url.username or os.environ.get("PGUSER") or getpass.getuser()
    if "connection refused" in low or ("no such file or directory" in low and "socket" in low):
        return StoreUnavailable(address, f"{address}: cannot reach the PostgreSQL server at {at}: connection "
                                         "refused (is the server running and listening there?)", exc)
    if any(m in low for m in ("resolve host", "translate host name", "name or service not known",
                              "nodename nor servname", "temporary failure in name resolution")):
        return StoreUnavailable(address, f"{address}: cannot reach the PostgreSQL server at {at}: unknown host "
                                         f"{url.host!r}", exc)
    if "timeout expired" in low or "timed out" in low:
        return StoreUnavailable(address, f"{address}: cannot reach the PostgreSQL server at {at}: no answer "
                                         f"within {CONNECT_TIMEOUT_S} s", exc)
    login = ("authentication failed", "no password supplied", "pg_hba.conf", "role \"")
    if any(m in low for m in login) and not ('database "' in low and "does not exist" in low):
        if "no password supplied" in low:
            reason = "the server asks for a password and none was given (in the URL, PGPASSWORD or ~/.pgpass)"
        elif "password authentication failed" in low:
            reason = "password authentication failed"
        else:
            reason = msg.split("FATAL:", 1)[-1].strip()
        return StoreUnavailable(address, f"{address}: the PostgreSQL server at {at} refused the login of "
                                         f"{user}@{url.host or 'localhost'}: {reason}", exc)
    if 'database "' in low and "does not exist" in low:
        return UserError(f"{address}: the PostgreSQL server at {at} has no database {url.database!r} (create it "
                         f"first, e.g. createdb -h {url.host or 'localhost'} -p {url.port or 5432} {url.database})")
    return None


# A server that does not answer is named after this long, not waited for (libpq's connect_timeout).
CONNECT_TIMEOUT_S = 10
# Two first runs on one empty PostgreSQL database: one creates the schema, the other waits and finds it.
_SCHEMA_LOCK = 0x1AB_5707E


class Store:
    def __init__(self, engine: Engine, path: StoreAddress) -> None:
        self.engine = engine
        self.path = path  # where the store is; str() shows a URL's password masked
        # Leases this Store holds: campaign id -> token. Writes of a held campaign's samples and its
        # heartbeat check the token in the database, so a process whose lease was taken over stops.
        self.leases: dict[int, str] = {}
        self.lost: set[int] = set()
        # The open's quick_check left the sample blocks to the reads (`open_existing(check_samples=False)`).
        self.samples_unchecked = False
        self._next_from: dict[int, int] = {}  # campaign id -> the last `next_step` found (all before it are done)

    # --- opening ---------------------------------------------------------------------------

    @staticmethod
    def _engine(address: StoreAddress) -> Engine:
        if address.file is not None:
            engine = create_engine(f"sqlite:///{address.file}", future=True)
            event.listen(engine, "connect", _on_connect)  # the pragmas are SQLite's
            return engine
        # pre_ping: a pooled connection the server dropped (a restart, pg_terminate_backend) is replaced
        # instead of failing the next write. The password stays inside the URL object.
        return create_engine(address.url, future=True, pool_pre_ping=True,
                             connect_args={"connect_timeout": CONNECT_TIMEOUT_S, "application_name": "labrunner"})

    @classmethod
    def create(cls, path: str | Path | StoreAddress) -> Store:
        """Open for writing, creating the schema if the file (or the server database) has none yet (a
        store may hold many campaigns)."""
        a = store_address(path)
        if a.is_server:
            return cls._create_on_server(a)
        p = a.file
        assert p is not None
        if p.exists() and p.stat().st_size > 0:
            store = cls.open_existing(a)
            return store
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            engine = cls._engine(a)
            metadata.create_all(engine)
            with engine.begin() as conn:
                conn.execute(insert(meta), [{"key": "schema_version", "value": str(SCHEMA_VERSION)},
                                            {"key": "created_by", "value": f"labrunner {__version__}"}])
        except IntegrityError:
            raise
        except _STORE_FAILURES as exc:
            raise StoreError(a, "create", exc) from exc
        log.info("store %s created (schema %d)", a, SCHEMA_VERSION)
        return cls(engine, a)

    @classmethod
    def _create_on_server(cls, a: StoreAddress) -> Store:
        """The schema created in a server database that has none (DDL is transactional there: all or
        nothing), then opened as an existing store."""
        engine = cls._engine(a)
        try:
            with engine.begin() as conn:
                conn.execute(select(func.pg_advisory_xact_lock(_SCHEMA_LOCK)))
                names = set(inspect(conn).get_table_names())
                if meta.name not in names:
                    clash = sorted(names & set(metadata.tables))
                    if clash:
                        raise UserError(f"{a}: not a labrunner database (it holds table {', '.join(clash)} but no "
                                        f"{meta.name}); give an empty database or a labrunner store")
                    metadata.create_all(conn)
                    conn.execute(insert(meta), [{"key": "schema_version", "value": str(SCHEMA_VERSION)},
                                                {"key": "created_by", "value": f"labrunner {__version__}"}])
                    log.info("store %s created (schema %d)", a, SCHEMA_VERSION)
        except _STORE_FAILURES as exc:
            refusal = _server_refusal(a, exc)
            raise (refusal or StoreError(a, "create", exc)) from None
        finally:
            engine.dispose()
        return cls.open_existing(a)

    @classmethod
    def open_existing(cls, path: str | Path | StoreAddress, *, check: bool = True,
                      check_samples: bool = True) -> Store:
        """Open a store (migrating a schema-1 one). `check`: run SQLite's quick_check first and raise
        `StoreDamage` when it finds damage (`labrunner check --db` opens without it, to report all).

        `check_samples=False` leaves the sample_blocks table (nearly all of a store's pages) out of that
        check, for a reader that reads a campaign's blocks anyway: the blocks' own pages are checked by
        reading them (SQLite refuses a damaged page), and a read that fails so runs the whole check and
        raises its `StoreDamage` (`_block_rows`). A store whose other tables are damaged is refused at
        the open as before."""
        a = store_address(path)
        if a.file is not None and not a.file.exists():
            raise UserError(f"{a}: database not found")
        if a.file is not None and a.file.is_dir():
            raise UserError(f"{a}: not a labrunner database")  # a directory
        engine = cls._engine(a)
        try:
            with engine.connect() as conn:
                version = conn.execute(select(meta.c.value).where(meta.c.key == "schema_version")).scalar()
        except _STORE_FAILURES as exc:
            engine.dispose()
            refusal = _server_refusal(a, exc)
            if refusal is not None:
                raise refusal from None
            cause = str(getattr(exc, "orig", None) or exc)
            if any(m in cause for m in _NOT_A_STORE):
                if a.is_server:
                    raise UserError(f"{a}: not a labrunner database (no table {meta.name}: the database holds no "
                                    "labrunner schema; labrunner run --db creates one in an empty database)") from None
                raise UserError(f"{a}: not a labrunner database") from None
            # A store that cannot be opened (a full disk for its -shm, a read-only directory, a damaged
            # file) is named as such, not mistaken for a foreign file.
            raise StoreError(a, "open", exc) from exc
        try:
            number = int(version) if version is not None else None
        except ValueError:
            number = None
        if number == 1:
            cls._migrate_from_1(engine, a)
        elif number != SCHEMA_VERSION:
            engine.dispose()
            if number is not None and number > SCHEMA_VERSION:
                raise UserError(f"{a}: database schema version {number} is newer than this labrunner's "
                                f"({SCHEMA_VERSION}): use the labrunner that wrote it, or a newer one")
            raise StoreDamage(f"{a}: table labrunner_meta: schema version {version!r} is not one labrunner "
                              f"wrote (this labrunner reads {SCHEMA_VERSION}): the store is damaged")
        store = cls(engine, a)
        try:
            if check:
                store.quick_check(skip=() if check_samples else (sample_blocks.name,))
            store.samples_unchecked = check and not check_samples
        except BaseException:
            engine.dispose()
            raise
        log.debug("store %s opened", a)
        return store

    @staticmethod
    def _migrate_from_1(engine: Engine, p: StoreAddress) -> None:
        """Schema 1 -> 2: add the lease columns. A campaign a version-1 process may still be running keeps
        that process as its holder (heartbeat: its last update), so the lease rules apply to it too."""
        try:
            with engine.begin() as conn:
                for column in ("lease_token VARCHAR", "lease_wall FLOAT"):
                    conn.execute(text(f"ALTER TABLE campaigns ADD COLUMN {column}"))
                conn.execute(update(campaigns).where(campaigns.c.status == "running", campaigns.c.pid.is_not(None))
                             .values(lease_token="schema-1", lease_wall=campaigns.c.updated_wall))
                conn.execute(update(meta).where(meta.c.key == "schema_version").values(value=str(SCHEMA_VERSION)))
        except _STORE_FAILURES as exc:
            engine.dispose()
            raise UserError(f"{p}: database schema version 1 must be migrated to {SCHEMA_VERSION} (a column is "
                            f"added), which failed: {getattr(exc, 'orig', None) or exc}; open it once where it can "
                            "be written (labrunner list DB does it)") from None
        log.info("store %s migrated from schema 1 to %d (campaign lease)", p, SCHEMA_VERSION)

    # --- damage ------------------------------------------------------------------------------

    def _pragma_check(self, pragma: str, tables: Sequence[str] | None = None) -> list[str]:
        """What SQLite's `quick_check`/`integrity_check` finds (empty: nothing), up to 20 lines; of the
        given tables (and their indexes) only, if given."""
        if self.engine.dialect.name != "sqlite":
            return []  # other servers keep their own page checksums
        try:
            with self.engine.connect() as conn:
                rows = [str(r) for arg in (["20"] if tables is None else tables)
                        for r in conn.exec_driver_sql(f"PRAGMA {pragma}({arg})").scalars()]
        except _STORE_FAILURES as exc:
            return [str(getattr(exc, "orig", None) or exc)]
        # A row may hold several lines and a "*** in database main ***" heading: one problem a line.
        lines = [line.strip() for r in rows for line in r.splitlines()
                 if line.strip() and not line.startswith("*** in database")]
        return [line for line in lines if line != "ok"]

    def quick_check(self, skip: Sequence[str] = ()) -> None:
        """Raise `StoreDamage` when SQLite's quick_check finds damaged pages (run on every open: it reads
        every page but skips the index-content comparison of integrity_check). `skip`: tables left out
        (checked table by table; damage found so is then named by the whole check)."""
        if skip:
            tables = [t.name for t in metadata.sorted_tables if t.name not in skip]
            if not self._pragma_check("quick_check", tables):
                return
        problems = self._pragma_check("quick_check")
        if problems:
            raise StoreDamage(f"{self.path}: the database is damaged: {self._locate_pages()}"
                              f"PRAGMA quick_check: {problems[0]}"
                              f"{f' (and {len(problems) - 1} more)' if len(problems) > 1 else ''}; "
                              f"run labrunner check --db {self.path}")

    def _locate_pages(self) -> str:
        """Which tables cannot be read through (the damaged pages' owners), as 'table T, campaign C: '."""
        found = []
        for table in metadata.sorted_tables:
            last: Any = None
            camp = table.c.id if table is campaigns else table.c.get("campaign_id")
            step = table.c.get("step_idx", table.c.get("idx")) if table is not campaigns else None
            try:
                with self.engine.connect() as conn:
                    # Every column is read (the damage may sit in a blob's overflow pages), in rowid order.
                    for row in conn.execute(select(*table.c)).mappings():
                        last = row
            except _STORE_FAILURES:
                where = f"table {table.name}"
                if last is not None and camp is not None:
                    where += f", after the row of campaign {last[camp.name]}"
                    if step is not None and last[step.name] is not None:
                        where += f" step {last[step.name]}"
                found.append(where)
        return ("in " + "; ".join(found) + ": ") if found else ""

    def damage_report(self) -> list[str]:
        """Everything `labrunner check --db` finds: PRAGMA integrity_check, then every stored JSON column
        and sample blob decoded. One line per problem, each naming campaign, table and step."""
        problems = [f"PRAGMA integrity_check: {line}" for line in self._pragma_check("integrity_check")]
        if problems:
            where = self._locate_pages()
            if where:
                problems.append(f"damaged pages {where.rstrip(': ')}")
        json_columns = {campaigns: ("lab_config", "sim_config"), events: ("detail",),
                        fits: ("provenance", "result")}
        for table, columns in json_columns.items():
            key = table.c.id
            camp = table.c.id if table is campaigns else table.c.campaign_id
            step_col = table.c.step_idx if "step_idx" in table.c else None
            q = select(key, camp, *([step_col] if step_col is not None else []), *[table.c[c] for c in columns])
            try:
                with self.engine.connect() as conn:
                    for row in conn.execute(q).mappings():
                        for c in columns:
                            value = row[c]
                            if value is None:
                                continue
                            try:
                                json.loads(value)
                            except (ValueError, TypeError) as exc:
                                step = row.get("step_idx")
                                problems.append(
                                    f"campaign {row[camp.name]}, table {table.name}, row {row['id']}"
                                    f"{f', step {step}' if step is not None else ''}: column {c} is not JSON "
                                    f"({exc})")
            except _STORE_FAILURES as exc:
                problems.append(f"table {table.name} cannot be read: {getattr(exc, 'orig', None) or exc}")
        try:
            with self.engine.connect() as conn:
                for row in conn.execute(select(sample_blocks)).mappings():
                    try:
                        _block_from_row(row, self.path)
                    except StoreDamage as exc:
                        problems.append(str(exc).removeprefix(f"{self.path}: "))
        except _STORE_FAILURES as exc:
            problems.append(f"table sample_blocks cannot be read: {getattr(exc, 'orig', None) or exc}")
        return problems

    def close(self) -> None:
        self.engine.dispose()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @contextmanager
    def _guard(self, doing: str) -> Iterator[None]:
        try:
            yield
        except IntegrityError:
            raise
        except _STORE_FAILURES as exc:
            raise StoreError(self.path, doing, exc) from exc

    @contextmanager
    def transaction(self) -> Iterator[Connection]:
        """A write transaction; a database that cannot be written raises `StoreError`."""
        with self._guard("write"), self.engine.begin() as conn:
            yield conn

    @contextmanager
    def reading(self) -> Iterator[Connection]:
        """A connection for reads; a database that cannot be read raises `StoreError`."""
        try:
            with self._guard("read"), self.engine.connect() as conn:
                yield conn
        except StoreError as exc:
            # Damage in the sample pages the open's check left to the reads (SQLITE_CORRUPT,
            # SQLITE_NOTADB): the whole check names it, as an open does.
            if self.samples_unchecked and any(m in exc.cause for m in _DAMAGED):
                self.quick_check()
            raise

    # --- campaigns ---------------------------------------------------------------------------

    def new_campaign(self, *, name: str, procedure_text: str, procedure_path: str | None, procedure_sha256: str,
                     lab_config: dict[str, Any], mode: str, sim_config: dict[str, Any] | None, clock_t0: float,
                     plan: Sequence[Any], lease_token: str | None = None, campaign_id: int | None = None) -> int:
        """A new campaign, its lease held by `lease_token` (this process) from the start if given; with
        the id `reserve_campaign_id` gave, if given."""
        now = time.time()
        try:
            return self._new_campaign(now, name=name, procedure_text=procedure_text, procedure_path=procedure_path,
                                      procedure_sha256=procedure_sha256, lab_config=lab_config, mode=mode,
                                      sim_config=sim_config, clock_t0=clock_t0, plan=plan, lease_token=lease_token,
                                      campaign_id=campaign_id)
        except IntegrityError:
            if campaign_id is None:
                raise
            # SQLite's reserved id (largest + 1) taken by a run that started at the same moment.
            raise UserError(f"{self.path}: another process created campaign {campaign_id} at the same moment; "
                            "run again") from None

    def _new_campaign(self, now: float, *, name: str, procedure_text: str, procedure_path: str | None,
                      procedure_sha256: str, lab_config: dict[str, Any], mode: str, sim_config: dict[str, Any] | None,
                      clock_t0: float, plan: Sequence[Any], lease_token: str | None, campaign_id: int | None) -> int:
        with self.transaction() as conn:
            cid = _inserted_id(conn.execute(insert(campaigns).values(
                **({} if campaign_id is None else {"id": campaign_id}), name=name, procedure_path=procedure_path,
                procedure_text=procedure_text,
                procedure_sha256=procedure_sha256, lab_config=json.dumps(lab_config), mode=mode,
                sim_config=json.dumps(sim_config) if sim_config is not None else None,
                software_version=__version__, status="running", created_wall=now, updated_wall=now,
                clock_t0=clock_t0, clock_last=clock_t0, pid=os.getpid(), host=os.uname().nodename,
                n_steps=len(plan), lease_token=lease_token, lease_wall=now if lease_token else None)))
            conn.execute(insert(steps), [
                {"campaign_id": cid, "idx": s.index, "orientation": s.orientation, "temperature_c": s.temperature_c,
                 "rate_dps": s.rate_dps, "status": "planned", "attempts": 0} for s in plan])
            conn.execute(insert(control).values(campaign_id=cid, request=None))
        if lease_token:
            self.leases[int(cid)] = lease_token
        log.info("campaign %d %r created in %s: %d steps (%s)", cid, name, self.path, len(plan), mode)
        return int(cid)

    def reserve_campaign_id(self) -> int:
        """The id the next `new_campaign(campaign_id=...)` will use, known before the campaign exists (its
        fit directory is named after it). SQLite gives the largest id + 1; a PostgreSQL sequence does
        not (a rolled-back insert uses a number up), so there the number is drawn from the sequence:
        taken for good, by this process alone."""
        with self.reading() as conn:
            if self.engine.dialect.name == "postgresql":
                return int(conn.execute(text("SELECT nextval(pg_get_serial_sequence('campaigns', 'id'))")).scalar_one())
            return int(conn.execute(select(func.max(campaigns.c.id))).scalar() or 0) + 1

    def campaign_ids(self) -> list[int]:
        with self.reading() as conn:
            return [int(r) for r in conn.execute(select(campaigns.c.id).order_by(campaigns.c.id)).scalars()]

    def resolve(self, campaign_id: int | None) -> int:
        """The campaign asked for, or the file's only/latest one."""
        ids = self.campaign_ids()
        if not ids:
            raise UserError(f"{self.path}: holds no campaign")
        if campaign_id is None:
            return ids[-1]
        if campaign_id not in ids:
            raise UserError(f"{self.path}: no campaign {campaign_id} (campaigns: {', '.join(map(str, ids))})")
        return campaign_id

    def campaign(self, campaign_id: int) -> CampaignInfo:
        with self.reading() as conn:
            row = conn.execute(select(campaigns).where(campaigns.c.id == campaign_id)).mappings().one_or_none()
        if row is None:
            raise UserError(f"{self.path}: no campaign {campaign_id}")
        d = dict(row)
        d["lab_config"] = _json(d["lab_config"], self.path, campaign_id, "campaigns", "lab_config")
        d["sim_config"] = _json(d["sim_config"] or None, self.path, campaign_id, "campaigns", "sim_config")
        return CampaignInfo(**d)

    def set_status(self, campaign_id: int, status: str, *, clock_last: float | None = None,
                   pid: int | None | str = "keep") -> None:
        values: dict[str, Any] = {"status": status, "updated_wall": time.time()}
        if clock_last is not None:
            values["clock_last"] = clock_last
        if pid != "keep":
            values["pid"] = pid
        self._not_lost(campaign_id)
        with self.transaction() as conn:
            conn.execute(_UPDATE_CAMPAIGN, {"w_id": campaign_id, **values})
        log.info("campaign %d: status %s", campaign_id, status)

    def heartbeat(self, campaign_id: int, clock_now: float) -> None:
        """The running process is alive; renews its lease (`LeaseLost` if another process took it)."""
        self._not_lost(campaign_id)
        with self.transaction() as conn:
            now = time.time()
            self._renew(conn, campaign_id, now, updated_wall=now, clock_last=clock_now)

    # --- the campaign lease --------------------------------------------------------------------

    @contextmanager
    def _exclusive(self) -> Iterator[Connection]:
        """A transaction that holds the database's write lock from its first statement.

        SQLite's default (deferred) transaction would let two processes both read a free lease before
        either writes; BEGIN IMMEDIATE takes the write lock first, so the second waits (busy_timeout)
        and then reads what the first wrote. Other servers lock the row (SELECT ... FOR UPDATE)."""
        with self._guard("lock"), self.engine.connect() as conn:
            if self.engine.dialect.name == "sqlite":
                conn.exec_driver_sql("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.rollback()
                raise
            conn.commit()

    def take_lease(self, campaign_id: int, token: str, decide: Any) -> LeaseHolder:
        """Take the campaign's lease for `token` if `decide(holder)` allows it (it raises to refuse).

        Read and write happen in one exclusive transaction, and the write is conditional on the token
        read (a compare-and-swap: rowcount 1 or nothing changed), so two processes cannot both win.
        Returns the holder it replaced."""
        with self._exclusive() as conn:
            row = conn.execute(select(campaigns.c.lease_token, campaigns.c.pid, campaigns.c.host,
                                      campaigns.c.lease_wall).where(campaigns.c.id == campaign_id)
                               .with_for_update()).one_or_none()
            if row is None:
                raise UserError(f"{self.path}: no campaign {campaign_id}")
            holder = LeaseHolder(campaign_id, row.lease_token, row.pid, row.host, row.lease_wall)
            decide(holder)
            now = time.time()
            same = (campaigns.c.lease_token.is_(None) if holder.token is None
                    else campaigns.c.lease_token == holder.token)
            taken = conn.execute(update(campaigns).where(campaigns.c.id == campaign_id, same).values(
                lease_token=token, lease_wall=now, updated_wall=now, pid=os.getpid(), host=os.uname().nodename))
            if taken.rowcount != 1:  # pragma: no cover - the exclusive transaction makes this unreachable
                raise UserError(f"{self.path}: campaign {campaign_id}: another process took the lease first")
        self.leases[campaign_id] = token
        self.lost.discard(campaign_id)
        log.info("campaign %d: lease taken (%s)", campaign_id, token[:8])
        return holder

    def release_lease(self, campaign_id: int) -> None:
        """Give up this process's lease (the campaign stays as it is); a lease taken over stays the taker's."""
        token = self.leases.pop(campaign_id, None)
        if token is None:
            return
        with self.transaction() as conn:
            conn.execute(update(campaigns).where(campaigns.c.id == campaign_id, campaigns.c.lease_token == token)
                         .values(lease_token=None, lease_wall=None))
        log.info("campaign %d: lease released", campaign_id)

    def lease_holder(self, campaign_id: int) -> LeaseHolder:
        with self.reading() as conn:
            row = conn.execute(select(campaigns.c.lease_token, campaigns.c.pid, campaigns.c.host,
                                      campaigns.c.lease_wall).where(campaigns.c.id == campaign_id)).one()
        return LeaseHolder(campaign_id, row.lease_token, row.pid, row.host, row.lease_wall)

    def _renew(self, conn: Connection, campaign_id: int, now: float, **also: Any) -> None:
        """Inside a write of a held campaign: renew the lease, or raise `LeaseLost` (the write rolls back).
        `also`: other columns of the campaign row to set (in the same statement when a lease is held)."""
        self._not_lost(campaign_id)  # a lease lost once stays lost: no write without it taken again
        token = self.leases.get(campaign_id)
        if token is None:  # a writer without a lease (tests driving a runner directly, labrunner abort)
            if also:
                conn.execute(_UPDATE_CAMPAIGN, {"w_id": campaign_id, **also})
            return
        kept = _hot(conn, _RENEW, {"w_id": campaign_id, "w_token": token, "lease_wall": now, **also})
        if kept.rowcount != 1:
            self.leases.pop(campaign_id, None)
            self.lost.add(campaign_id)
            log.warning("campaign %d: lease lost to another process", campaign_id)
            raise LeaseLost(self.path, campaign_id)

    def _not_lost(self, campaign_id: int) -> None:
        if campaign_id in self.lost:
            raise LeaseLost(self.path, campaign_id)

    # --- steps and samples ---------------------------------------------------------------------

    def next_step(self, campaign_id: int) -> int | None:
        """Index of the first step not yet recorded (None: all done)."""
        # A step once done stays done (no write sets another status), so the steps before the one last
        # found are done still, whoever recorded since.
        start = self._next_from.get(campaign_id, 0)
        with self.reading() as conn:
            found = _hot(conn, _NEXT_STEP, {"w_campaign": campaign_id, "w_from": start}).scalar()
        if found is not None:
            self._next_from[campaign_id] = int(found)
        return found

    def last_time(self, campaign_id: int) -> float:
        """Campaign time of the latest event (every transition and record writes one)."""
        with self.reading() as conn:
            return float(conn.execute(select(func.max(events.c.t_s)).where(
                events.c.campaign_id == campaign_id)).scalar() or 0.0)

    def last_moment(self, campaign_id: int) -> float:
        """Campaign time of the latest thing stored: an event, a record's or a monitor stretch's last
        sample, or a chamber or table reading taken with one (0.0 for an empty campaign).

        Monitor stretches are stored while soaking with no event between them, so the latest event
        can lie far behind what is stored; a resumed dry run must start after all of it."""
        latest = self.last_time(campaign_id)
        # Blocks of one session follow each other: the latest starts are the only candidates for the
        # latest end (a block is at most a record long). The margin covers the sessions' order.
        q = (select(sample_blocks.c.t0_s, sample_blocks.c.rate_hz, sample_blocks.c.counter, sample_blocks.c.chamber,
                    sample_blocks.c.table)
             .where(sample_blocks.c.campaign_id == campaign_id).order_by(sample_blocks.c.t0_s.desc()).limit(50))
        with self.reading() as conn:
            for t0, rate_hz, counter, chamber, table in conn.execute(q):
                offsets = np.frombuffer(counter, dtype="<i4")
                ends = [t0 + (float(offsets[-1]) / rate_hz if offsets.size else 0.0)]
                for readings in (chamber, table):
                    pairs = np.frombuffer(readings, dtype="<f8").reshape(-1, 2)
                    if pairs.size:
                        ends.append(float(pairs[:, 0].max()))
                latest = max(latest, *ends)
        return float(latest)

    def max_run(self, campaign_id: int) -> int:
        with self.reading() as conn:
            return int(conn.execute(select(func.max(sample_blocks.c.run)).where(
                sample_blocks.c.campaign_id == campaign_id)).scalar() or 0)

    def note_attempt(self, campaign_id: int, step_idx: int) -> None:
        with self.transaction() as conn:
            _hot(conn, _ATTEMPT, {"w_campaign": campaign_id, "w_idx": step_idx})

    @staticmethod
    def _block_row(campaign_id: int, block: SampleBlock) -> dict[str, Any]:
        counter = np.asarray(block.counter, dtype=np.int64)
        offsets = (counter - counter[0]) if counter.size else counter
        la, lg, lt = block.lsb if block.lsb is not None else (None, None, None)
        return {
            "campaign_id": campaign_id, "kind": block.kind, "step_idx": block.step_idx, "run": block.run,
            "orientation": block.orientation, "t0_s": block.t0_s, "rate_hz": block.rate_hz, "n": int(counter.size),
            "counter": np.ascontiguousarray(offsets, dtype="<i4").tobytes(),
            "encoding": "i16" if block.lsb is not None else "f32", "accel_lsb": la, "gyro_lsb": lg, "temp_lsb": lt,
            "accel_g": _encode(block.accel_g, la), "gyro_dps": _encode(block.gyro_dps, lg),
            "temp_c": _encode(block.temp_c, lt), "chamber": _f64(block.chamber), "table": _f64(block.table),
        }

    def commit_record(self, campaign_id: int, block: SampleBlock, *, dropped: int, corrupt: int, t_end: float,
                      event_message: str, detail: dict[str, Any] | None = None) -> None:
        """Store a record step's samples, mark the step done and log it: all or nothing."""
        assert block.kind == "record" and block.step_idx is not None
        chamber_mean = float(np.mean(block.chamber[:, 1])) if block.chamber.size else None
        with self.transaction() as conn:
            self._renew(conn, campaign_id, time.time())
            _hot(conn, _INSERT_BLOCK, self._block_row(campaign_id, block))
            _hot(conn, _UPDATE_STEP, {
                "w_campaign": campaign_id, "w_idx": block.step_idx, "status": "done", "run": block.run,
                "t_start": block.t0_s, "t_end": t_end, "n_samples": len(block), "dropped": dropped, "corrupt": corrupt,
                "imu_temp_c": float(np.mean(block.temp_c)) if len(block) else None, "chamber_c": chamber_mean})
            self._event(conn, campaign_id, t_end, "record", event_message, step_idx=block.step_idx, detail=detail)

        log.debug("campaign %d: step %d committed, %d samples (%d dropped, %d corrupt)", campaign_id,
                  block.step_idx, len(block), dropped, corrupt)

    def save_monitor(self, campaign_id: int, block: SampleBlock) -> None:
        with self.transaction() as conn:
            self._renew(conn, campaign_id, time.time())
            _hot(conn, _INSERT_BLOCK, self._block_row(campaign_id, block))

    # --- events and control ----------------------------------------------------------------------

    @staticmethod
    def _event(conn: Connection, campaign_id: int, t_s: float, kind: str, message: str, *, state: str | None = None,
               step_idx: int | None = None, detail: dict[str, Any] | None = None, wall: float | None = None) -> None:
        log.debug("campaign %d event at t=%.1f s [%s]: %s", campaign_id, t_s, kind, message)
        _hot(conn, _INSERT_EVENT, {
            "campaign_id": campaign_id, "t_s": t_s, "wall": time.time() if wall is None else wall, "kind": kind,
            "state": state, "step_idx": step_idx, "message": message, "detail": json.dumps(detail) if detail else None})

    def event(self, campaign_id: int, t_s: float, kind: str, message: str, *, state: str | None = None,
              step_idx: int | None = None, detail: dict[str, Any] | None = None, wall: float | None = None) -> None:
        """Log one event; `wall` is when it happened if it is written later (default: now)."""
        self._not_lost(campaign_id)
        with self.transaction() as conn:
            self._event(conn, campaign_id, t_s, kind, message, state=state, step_idx=step_idx, detail=detail,
                        wall=wall)

    def write_events(self, campaign_id: int, rows: Sequence[dict[str, Any]]) -> None:
        """Log events held back while the store could not be written, in order, all or none.

        Each row has the keyword arguments of `event` (t_s, kind, message, state, step_idx, detail, wall)."""
        if not rows:
            return
        self._not_lost(campaign_id)
        with self.transaction() as conn:
            for row in rows:
                self._event(conn, campaign_id, **row)

    def request(self, campaign_id: int, what: str | None) -> None:
        with self.transaction() as conn:
            conn.execute(update(control).where(control.c.campaign_id == campaign_id).values(
                request=what, requested_wall=time.time() if what else None))

    def pending_request(self, campaign_id: int) -> str | None:
        with self.reading() as conn:
            return _hot(conn, _PENDING, {"w_campaign": campaign_id}).scalar()

    # --- fits ------------------------------------------------------------------------------------

    def save_fit(self, campaign_id: int, result: dict[str, Any], provenance: dict[str, Any]) -> int:
        with self.transaction() as conn:
            return _inserted_id(conn.execute(insert(fits).values(
                campaign_id=campaign_id, created_wall=time.time(), software_version=__version__,
                provenance=json.dumps(provenance), result=json.dumps(result))))

    def find_fit(self, campaign_id: int, provenance: dict[str, Any], keys: Sequence[str]) -> int | None:
        """The id of a stored fit of the campaign whose provenance agrees with `provenance` on `keys`
        (the same data), or None."""
        with self.reading() as conn:
            rows = conn.execute(select(fits.c.id, fits.c.provenance).where(fits.c.campaign_id == campaign_id)
                                .order_by(fits.c.id)).fetchall()
        want = {k: provenance.get(k) for k in keys}
        for fit_id, stored in rows:
            try:
                got = json.loads(stored)
            except ValueError:  # an unreadable provenance is no match
                continue
            if isinstance(got, dict) and {k: got.get(k) for k in keys} == want:
                return int(fit_id)
        return None

    def fits_frame(self, campaign_id: int) -> pd.DataFrame:
        import pandas as pd

        with self.reading() as conn:
            return pd.read_sql(select(fits.c.id, fits.c.created_wall, fits.c.software_version, fits.c.provenance)
                               .where(fits.c.campaign_id == campaign_id).order_by(fits.c.id), conn)

    # --- readers ------------------------------------------------------------------------------------

    def steps_frame(self, campaign_id: int) -> pd.DataFrame:
        import pandas as pd

        with self.reading() as conn:
            return pd.read_sql(select(steps).where(steps.c.campaign_id == campaign_id).order_by(steps.c.idx), conn)

    def step_counts(self, campaign_id: int) -> tuple[int, int]:
        """Steps planned and steps recorded (status done) of a campaign."""
        q = select(func.count(), func.coalesce(func.sum(case((steps.c.status == "done", 1), else_=0)), 0)).where(
            steps.c.campaign_id == campaign_id)
        with self.reading() as conn:
            planned, done = conn.execute(q).one()
        return int(planned), int(done)

    def event_messages(self, campaign_id: int, containing: str) -> list[str]:
        """The messages of a campaign's events that contain `containing`, in event order (without
        reading the other events: a campaign logs tens of thousands)."""
        pattern = containing.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        q = (select(events.c.message).where(events.c.campaign_id == campaign_id,
                                            events.c.message.like(f"%{pattern}%", escape="\\"))
             .order_by(events.c.id))
        with self.reading() as conn:
            # LIKE ignores ASCII letter case on SQLite: the exact test is Python's.
            return [m for m in conn.execute(q).scalars() if containing in m]

    def events_frame(self, campaign_id: int, last: int | None = None) -> pd.DataFrame:
        import pandas as pd

        q = select(events).where(events.c.campaign_id == campaign_id)
        if last:
            q = q.order_by(events.c.id.desc()).limit(last)
        with self.reading() as conn:
            frame = pd.read_sql(q, conn)
        return frame.sort_values("id").reset_index(drop=True)

    def blocks(self, campaign_id: int, kinds: Sequence[str] = ("record",)) -> Iterator[SampleBlock]:
        for row in self._block_rows(campaign_id, kinds):
            yield _block_from_row(row, self.path)

    def stored_blocks(self, campaign_id: int, kinds: Sequence[str] = ("record",)) -> Iterator[StoredBlock]:
        """`blocks`, each decoded only a slice at a time by its reader (`StoredBlock`)."""
        for row in self._block_rows(campaign_id, kinds):
            yield _stored_block(row, self.path)

    def _block_rows(self, campaign_id: int, kinds: Sequence[str]) -> Iterator[Any]:
        """The stored block rows of the given kinds in time order (blobs not yet checked)."""
        q = (select(sample_blocks).where(sample_blocks.c.campaign_id == campaign_id,
                                         sample_blocks.c.kind.in_(list(kinds)))
             .order_by(sample_blocks.c.t0_s, sample_blocks.c.id))
        with self.reading() as conn:
            result = conn.execute(q)
            keys = list(result.keys())
            for values in result:  # as dicts: ~35 lookups a block, cheaper than a RowMapping's
                yield dict(zip(keys, values))

    def _one_lsb(self, campaign_id: int, kinds: Sequence[str]) -> tuple[float, float, float] | None:
        """The LSB sizes (accel, gyro, temp) when every block of these kinds holds int16 counts of the
        same sizes (one IMU: what a recorded campaign is), else None."""
        q = (select(sample_blocks.c.encoding, sample_blocks.c.accel_lsb, sample_blocks.c.gyro_lsb,
                    sample_blocks.c.temp_lsb).distinct()
             .where(sample_blocks.c.campaign_id == campaign_id, sample_blocks.c.kind.in_(list(kinds))).limit(2))
        with self.reading() as conn:
            found = conn.execute(q).fetchall()
        if len(found) != 1 or found[0][0] != "i16" or not all(isinstance(v, float) and v > 0 for v in found[0][1:]):
            return None
        return (float(found[0][1]), float(found[0][2]), float(found[0][3]))

    def sample_count(self, campaign_id: int, kinds: Sequence[str] = ("record",)) -> int:
        """Samples stored in a campaign's blocks of the given kinds (from the block rows, no blob read)."""
        q = select(func.coalesce(func.sum(sample_blocks.c.n), 0)).where(
            sample_blocks.c.campaign_id == campaign_id, sample_blocks.c.kind.in_(list(kinds)))
        with self.reading() as conn:
            return int(conn.execute(q).scalar_one())

    def time_range(self, campaign_id: int, kinds: Sequence[str] = ("record",)) -> tuple[float, float]:
        """The first and last sample times of a campaign's blocks of these kinds, as the frame's `t_s`
        has them, from the block rows and each counter blob's first and last offsets (no sample blob is
        read); (nan, nan) when there are no samples. A block's counters ascend (its first sample is
        its earliest, its last its latest)."""
        c = sample_blocks.c
        ends = (func.substr(c.counter, 1, 4), func.substr(c.counter, func.length(c.counter) - 3, 4))
        q = (select(c.t0_s, c.rate_hz, *ends).where(c.campaign_id == campaign_id, c.kind.in_(list(kinds)), c.n > 0))
        lo, hi = np.inf, -np.inf
        with self.reading() as conn:
            for t0, rate_hz, first, last in conn.execute(q):
                if not isinstance(first, bytes) or len(first) != 4 or not isinstance(last, bytes) or len(last) != 4:
                    continue  # a damaged counter blob: the read of the samples names it
                offsets = np.frombuffer(first + last, dtype="<i4")
                end = np.add(np.divide(np.subtract(offsets[1:], offsets[0], dtype=np.float64), rate_hz), t0)
                lo, hi = min(lo, float(t0)), max(hi, float(end[0]))
        return (lo, hi) if lo <= hi else (float("nan"), float("nan"))

    def samples_frame(self, campaign_id: int, include_monitor: bool = False, with_steps: bool = False,
                      remount_c: float | None = None, categorical: bool = False, counts: bool = False) -> pd.DataFrame:
        """All samples in the campaign CSV columns (records; with monitor rows if asked), time-ordered.

        `run` is int64, the numbers float64, orientation text; with `categorical` (what `campaign_data`
        reads for the analyses) orientation is categorical: the six orientations first, then any other
        label a block holds, for the validation to name; one byte a row instead of an object.

        With `counts` the IMU channels (accelerometer, gyro, temperature) stay the stored int16 counts
        with their LSB (`ScaledFloatArray`: float64 to pandas, the same values bit for bit, a quarter
        of the memory) when every block holds counts of the same LSB sizes; float64 otherwise.

        `with_steps` adds, per row, `kind` (record or monitor), the sequencer's `state`, the
        `step_idx` of its step, the chamber `setpoint_c` and the commanded table rate `rate_cmd_dps`
        (see `_with_steps`; `remount_c` is the procedure's remount temperature)."""
        kinds = ("record", "monitor") if include_monitor else ("record",)
        # Columns preallocated to the stored sample count and filled block by block: no per-row
        # Python objects (orientation is one code per block) and no concatenation copy.
        frame, _ = self._samples(campaign_id, kinds, categorical=categorical, counts=counts, with_steps=with_steps)
        return self._with_steps(campaign_id, frame, remount_c) if with_steps else frame

    def _samples(self, campaign_id: int, kinds: Sequence[str], *, categorical: bool, counts: bool,
                 with_steps: bool = False) -> tuple[pd.DataFrame, _BlockColumns]:
        """`samples_frame` without the step columns, and the columns it was made of."""
        total = self.sample_count(campaign_id, kinds)
        cols = _BlockColumns(total, None, list(ORIENTATIONS), self.path, counts=counts, with_steps=with_steps)
        for row in self._block_rows(campaign_id, kinds):
            if not cols.add(row):
                break
        return cols.frame(categorical, sort="monitor" in kinds), cols

    def frames(self, campaign_id: int, *, max_rows: int = 1 << 20, include_monitor: bool = False,
               categorical: bool = True, counts: bool = True, min_gap_s: float | None = None,
               rows: int | None = None) -> Iterator[pd.DataFrame]:
        """`samples_frame(campaign_id, include_monitor=..., categorical=..., counts=...)` a bounded number of
        rows at a time: `pd.concat(frames(...))` equals it (index included: each chunk's RangeIndex
        continues the previous one's, so a chunk's first index is its first row's position in the campaign).

        Chunks hold whole blocks and start at a block boundary. A chunk closes at the first boundary
        after it holds `max_rows` rows where the next block starts more than `min_gap_s` seconds after
        the chunk's last sample (None: at any boundary; then a chunk exceeds `max_rows` by at most its
        last block). With monitor rows (time-ordered like `samples_frame`: each chunk sorted), a chunk
        also closes only where no sample of it is later than the next block's start, so the chunks'
        rows are in the order of the whole sort. The IMU channels are counts when the whole campaign's
        blocks share one LSB (as `samples_frame` decides), so every chunk has the same dtypes; a label
        outside the six orientations adds a category from the chunk that first holds it on.

        `rows`: read at most the campaign's first `rows` samples (a count taken earlier): passes over a
        campaign that is still being recorded all see the rows the first pass saw (blocks are appended in
        time order, so later blocks are the ones left out)."""
        if max_rows < 1:
            raise ValueError(f"max_rows must be at least 1, not {max_rows}")
        kinds = ("record", "monitor") if include_monitor else ("record",)
        total = self.sample_count(campaign_id, kinds)
        if rows is not None:
            total = min(total, rows)
        lsb = self._one_lsb(campaign_id, kinds) if counts else None
        labels = list(ORIENTATIONS)  # shared by the chunks: a category once added stays
        pending: list[Any] = []
        held = 0  # rows in pending
        last = -np.inf  # the latest sample time in pending
        read = 0  # rows taken (what was counted is read, as samples_frame does)
        start = 0  # index of the chunk's first row

        def flush() -> pd.DataFrame:
            nonlocal pending, held, last, start
            cols = _BlockColumns(held, lsb, labels, self.path, counts=lsb is not None)
            for r in pending:
                if not cols.add(r):
                    break
            frame = cols.frame(categorical, sort=include_monitor, start=start)
            start += len(frame)
            pending, held, last = [], 0, -np.inf
            return frame

        for row in self._block_rows(campaign_id, kinds):
            lsb_row = _checked_row(row, self.path)  # the blobs hold what the row says (the end time reads one)
            n = int(row["n"])
            if n == 0:
                continue
            if read + n > total or (lsb is not None and lsb_row != lsb):
                break  # a block written since the count: not read (as samples_frame)
            t0 = row["t0_s"]
            if held >= max_rows and (min_gap_s is None or t0 - last > min_gap_s) and (
                    not include_monitor or last <= t0):
                yield flush()
            pending.append(row)
            held += n
            read += n
            last = max(last, _end_time(row))
        if pending:
            yield flush()

    def _with_steps(self, campaign_id: int, frame: pd.DataFrame, remount_c: float | None) -> pd.DataFrame:
        """Fill `state`, `step_idx`, `setpoint_c` and `rate_cmd_dps` of time-ordered rows.

        A record row is its step's, recorded in state `recording` at the step's rate. A monitor row
        (1 s means while the chamber moves) takes the sequencer's state and step from the last
        transition before it: `mounting` (waiting for the remount temperature, the previous
        orientation still mounted: setpoint `remount_c`), or `ramping`/`soaking` towards the step's
        temperature; the table is stopped then (commanded rate 0)."""
        import pandas as pd

        step = frame["step_idx"].to_numpy(dtype=float).copy()
        monitor = np.isnan(step)
        state = np.full(step.size, "recording", dtype=object)
        state[monitor] = None
        if monitor.any():
            ev = self.events_frame(campaign_id)
            ev = ev[ev.kind == "transition"].sort_values(["t_s", "id"], kind="stable")
            t_ev = ev.t_s.to_numpy(dtype=float)
            pos = np.searchsorted(t_ev, frame["t_s"].to_numpy(dtype=float)[monitor], side="right") - 1
            found = pos >= 0
            at = np.maximum(pos, 0)
            ev_step = ev.step_idx.to_numpy(dtype=float)
            ev_state = ev.state.to_numpy(dtype=object)
            step[monitor] = np.where(found, ev_step[at] if t_ev.size else np.nan, np.nan)
            state[monitor] = np.where(found, ev_state[at] if t_ev.size else None, None)
        plan = self.steps_frame(campaign_id).set_index("idx")
        known = ~np.isnan(step)
        setpoint = np.full(step.size, np.nan)
        rate = np.full(step.size, np.nan)
        idx = step[known].astype(np.int64)
        setpoint[known] = plan["temperature_c"].reindex(idx).to_numpy(dtype=float)
        rate[known] = plan["rate_dps"].reindex(idx).to_numpy(dtype=float)
        rate[monitor] = 0.0
        setpoint[state == "mounting"] = np.nan if remount_c is None else remount_c
        frame["state"] = state
        frame["step_idx"] = pd.array(step, dtype="Float64").astype("Int64")  # NaN -> <NA>
        frame["setpoint_c"] = setpoint
        frame["rate_cmd_dps"] = rate
        return frame[[*COLUMNS, *STEP_COLUMNS]]

    def campaign_data(self, campaign_id: int | None = None, include_monitor: bool = False) -> Any:
        """Samples as validated campaign data with provenance (what `labrunner fit`/`diagnose` read)."""

        from labrunner.campaign_csv import read_campaign
        from labrunner.data_source import CampaignData

        cid = self.resolve(campaign_id)
        info = self.campaign(cid)
        kinds = ("record", "monitor") if include_monitor else ("record",)
        frame, cols = self._samples(cid, kinds, categorical=True, counts=True)
        if frame.empty:
            raise UserError(f"{self.path}: campaign {cid} has no recorded samples yet")
        # (read_campaign keeps the int16-count columns as they are: finite by construction.)
        frame = read_campaign(frame, name=f"{self.path} campaign {cid}")
        # The time range without a pass over the rows: with monitor rows the frame is in time order;
        # records only, validated, their times ascend within each run, so within each block, and the
        # earliest block start and the latest block end are the time column's minimum and maximum.
        t = frame["t_s"].to_numpy()
        t_range = [float(t[0]), float(t[-1])] if include_monitor else [cols.first_t, cols.last_t]
        return CampaignData(frame=frame, store=self.path, provenance={
            "source": str(self.path.resolve()), "kind": "store", "campaign_id": cid, "campaign": info.name,
            "procedure_sha256": info.procedure_sha256, "status": info.status, "rows": len(frame),
            "t_range_s": t_range,
            "recorded_with": info.software_version,
        })


def interp_readings(t: np.ndarray, readings: np.ndarray, default: float = float("nan"),
                    out: np.ndarray | None = None) -> np.ndarray:
    """Instrument readings taken during a block, interpolated to the sample times (into `out` if given)."""
    if readings.size == 0:
        return _filled(t.size, default, out)
    first = readings[0, 1]
    if readings.shape[0] == 1:
        return _filled(t.size, first, out)
    # A steady reading (the table's rate, a soak's chamber): np.interp gives that value bit for bit
    # (slope 0: 0 * dx + value), except for -0.0 (0.0 + -0.0 is 0.0), so that one is interpolated.
    if (readings[:, 1] == first).all() and (first != 0 or not np.signbit(first)):
        return _filled(t.size, first, out)
    if out is None:
        return np.interp(t, readings[:, 0], readings[:, 1])
    out[:] = np.interp(t, readings[:, 0], readings[:, 1])
    return out


def _filled(n: int, value: float, out: np.ndarray | None) -> np.ndarray:
    if out is None:
        return np.full(n, value)
    out.fill(value)
    return out


__all__ = ["CampaignInfo", "LeaseHolder", "LeaseLost", "SampleBlock", "Store", "StoreDamage", "StoreError",
           "StoredBlock"]
