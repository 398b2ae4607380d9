"""SQL run on a store's own database, whichever backend, for tests that plant or read rows directly."""

from pathlib import Path

from sqlalchemy import create_engine, text

from labrunner.store_address import StoreAddress, store_address


def store_rows(db: str | Path | StoreAddress, statement: str, **params: object) -> list[tuple]:
    """The rows of `statement` (none for a write), committed; the engine is disposed of after."""
    engine = create_engine(store_address(db).url)
    try:
        with engine.begin() as conn:
            result = conn.execute(text(statement), params)
            return [tuple(r) for r in result] if result.returns_rows else []
    finally:
        engine.dispose()
