"""Where analysis data comes from: a campaign CSV or a labrunner SQLite store, as one frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from labrunner.campaign_csv import CampaignDataError, read_campaign

SQLITE_MAGIC = b"SQLite format 3\x00"


@dataclass
class CampaignData:
    """Validated campaign rows (campaign CSV columns) and where they came from."""

    frame: pd.DataFrame
    provenance: dict[str, Any] = field(default_factory=dict)


def is_sqlite(path: str | Path) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(16) == SQLITE_MAGIC
    except OSError:
        return False


def load_campaign_data(path: str | Path, campaign: int | None = None, *, include_monitor: bool = False) -> CampaignData:
    """Load a campaign CSV or a store database (its latest campaign, or `campaign`).

    From a store, `include_monitor` adds the 1 s monitor rows logged while ramping and soaking
    (what a diagnosis of thermal lag or hysteresis needs); a fit uses the record steps only.
    """
    p = Path(path)
    if not p.exists():
        raise CampaignDataError(str(p), "file not found")
    if p.is_dir():
        raise CampaignDataError(str(p), "is a directory; expected a campaign CSV or a labrunner database file")
    if is_sqlite(p):
        from labrunner.store import Store

        with Store.open_existing(p) as store:
            return store.campaign_data(campaign, include_monitor=include_monitor)
    frame = read_campaign(p)
    return CampaignData(frame=frame, provenance={"source": str(p.resolve()), "kind": "csv", "rows": len(frame)})
