"""Are two dry-run stores the same campaign, bit for bit? (issue 15: a recording speed-up must not change it)

Usage: python tools/compare_stores.py A.db B.db

Compares every sample block (all columns: the blobs as bytes, floats by their bits), every step, every
event and each campaign row, leaving out only what a second run cannot repeat: wall-clock times (events'
`wall`, the campaign's created/updated/lease times), the process (pid, host, lease token) and the procedure's
path. Prints a SHA-256 per table and the first differing row of each table that differs; exits 1 if any does.
"""

from __future__ import annotations

import hashlib
import sqlite3
import struct
import sys
from collections.abc import Iterator
from typing import Any

# Columns a second run of the same campaign cannot repeat.
SKIP = {
    "campaigns": {"created_wall", "updated_wall", "pid", "host", "lease_token", "lease_wall", "procedure_path"},
    "events": {"wall"},
}
TABLES = ("campaigns", "steps", "sample_blocks", "events")
ORDER = {"campaigns": "id", "steps": "campaign_id, idx", "sample_blocks": "id", "events": "id"}


def _columns(con: sqlite3.Connection, table: str) -> list[str]:
    names = [r[1] for r in con.execute(f'PRAGMA table_info("{table}")')]
    return [c for c in names if c not in SKIP.get(table, set())]


def _rows(con: sqlite3.Connection, table: str, cols: list[str]) -> Iterator[tuple[Any, ...]]:
    quoted = ", ".join(f'"{c}"' for c in cols)
    yield from con.execute(f'SELECT {quoted} FROM "{table}" ORDER BY {ORDER[table]}')


def _bits(value: Any) -> bytes:
    """A value as bytes that differ whenever the value's bits do (a float by its IEEE bits: -0.0 != 0.0)."""
    if value is None:
        return b"N"
    if isinstance(value, float):
        return b"F" + struct.pack("<d", value)
    if isinstance(value, int):
        return b"I" + str(value).encode()
    if isinstance(value, bytes):
        return b"B" + len(value).to_bytes(8, "little") + value
    text = str(value).encode()
    return b"S" + len(text).to_bytes(8, "little") + text


def compare(a_path: str, b_path: str) -> bool:
    a = sqlite3.connect(f"file:{a_path}?mode=ro", uri=True)
    b = sqlite3.connect(f"file:{b_path}?mode=ro", uri=True)
    same = True
    for table in TABLES:
        cols = _columns(a, table)
        if cols != _columns(b, table):
            print(f"{table}: columns differ: {cols} vs {_columns(b, table)}")
            same = False
            continue
        ha, hb = hashlib.sha256(), hashlib.sha256()
        n_a = n_b = 0
        first: str | None = None
        ia, ib = _rows(a, table, cols), _rows(b, table, cols)
        while True:
            ra, rb = next(ia, None), next(ib, None)
            if ra is None and rb is None:
                break
            if ra is not None:
                n_a += 1
                ha.update(b"".join(_bits(v) for v in ra))
            if rb is not None:
                n_b += 1
                hb.update(b"".join(_bits(v) for v in rb))
            if first is None and (ra is None or rb is None or [_bits(v) for v in ra] != [_bits(v) for v in rb]):
                if ra is None or rb is None:
                    first = f"row {max(n_a, n_b)}: only in {'B' if ra is None else 'A'}"
                else:
                    diff = [c for c, x, y in zip(cols, ra, rb, strict=True) if _bits(x) != _bits(y)]
                    first = f"row {n_a}: {', '.join(diff)} differ ({ra[:4]} / {rb[:4]})"
        verdict = "same" if ha.digest() == hb.digest() and n_a == n_b else "DIFFERENT"
        print(f"{table:14s} {n_a:8d} / {n_b:8d} rows  {ha.hexdigest()[:16]} / {hb.hexdigest()[:16]}  {verdict}")
        if verdict != "same":
            same = False
            print(f"  first difference: {first}")
    return same


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__)
        return 2
    return 0 if compare(argv[0], argv[1]) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
