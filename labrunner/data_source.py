"""Where analysis data comes from: a campaign CSV or a labrunner store (a SQLite file or a PostgreSQL URL),
as one frame."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from labrunner.campaign_csv import CampaignDataError, read_campaign
from labrunner.store_address import StoreAddress, is_store, is_url, store_address


@dataclass
class CampaignData:
    """Validated campaign rows (campaign CSV columns) and where they came from."""

    frame: pd.DataFrame
    provenance: dict[str, Any] = field(default_factory=dict)
    # The store read, password and all, to store a fit back into (provenance["source"] shows it masked).
    store: StoreAddress | None = field(default=None, repr=False, compare=False)


def step_progress(store: Any, campaign_id: int) -> dict[str, int]:
    """Steps planned and recorded (status done) of a stored campaign: a fit says when they differ."""
    steps = store.steps_frame(campaign_id)
    return {"steps_planned": int(len(steps)), "steps_recorded": int((steps["status"] == "done").sum())}


def load_campaign_data(path: str | Path | StoreAddress, campaign: int | None = None, *,
                       include_monitor: bool = False) -> CampaignData:
    """Load a campaign CSV or a store database (its latest campaign, or `campaign`).

    From a store, `include_monitor` adds the 1 s monitor rows logged while ramping and soaking
    (what a diagnosis of thermal lag or hysteresis needs); a fit uses the record steps only.
    """
    if isinstance(path, StoreAddress) or is_url(path):
        return _from_store(store_address(path), campaign, include_monitor)
    p = Path(path)
    if not p.exists():
        raise CampaignDataError(str(p), "file not found")
    if p.is_dir():
        raise CampaignDataError(str(p), "is a directory; expected a campaign CSV or a labrunner database file")
    if is_store(p):
        return _from_store(store_address(p), campaign, include_monitor)
    frame = read_campaign(p)
    return CampaignData(frame=frame, provenance={"source": str(p.resolve()), "kind": "csv", "rows": len(frame)})


def _from_store(address: StoreAddress, campaign: int | None, include_monitor: bool) -> CampaignData:
    from labrunner.store import Store

    with Store.open_existing(address) as store:
        data = store.campaign_data(campaign, include_monitor=include_monitor)
        data.provenance.update(step_progress(store, int(data.provenance["campaign_id"])))
        data.frame = mark_power_ons(data.frame, store.events_frame(int(data.provenance["campaign_id"])))
        return data


def mark_power_ons(frame: pd.DataFrame, events: pd.DataFrame) -> pd.DataFrame:
    """The store's power-on events as the campaign CSV's optional `power_on` column: 1 on the first
    row of each run the sequencer powered the IMU on for (its "powered on (run N)" event)."""
    import re

    runs = {int(m.group(1)) for text in events.get("message", pd.Series(dtype=str)).astype(str)
            if (m := re.search(r"powered on \(run (\d+)\)", text))}
    run = frame["run"].to_numpy()
    # The first row of each run: where the run changes, when no run comes back later (a store's rows
    # are in time order); else by hashing every row's run.
    change = np.flatnonzero(np.concatenate(([True], run[1:] != run[:-1])))
    if np.unique(run[change]).size == change.size:
        first = np.zeros(run.size, dtype=bool)
        first[change] = True
    else:
        first = ~frame["run"].duplicated().to_numpy()
    at = np.flatnonzero(first)
    mark = np.zeros(run.size, dtype=np.int8)
    mark[at[np.isin(run[at], np.fromiter(runs, dtype=np.int64, count=len(runs)))]] = 1
    return frame.assign(power_on=mark)
