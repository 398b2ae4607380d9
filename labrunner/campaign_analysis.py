"""The analyses of a campaign from Python: the fit and the diagnosis, as `labrunner fit` and `diagnose`.

Data come from a store's campaign or a campaign CSV (`load_data`), validated, with provenance; a
fit of a store's campaign is stored in it with that provenance.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labrunner.errors import UserError
from labrunner.output_paths import check_output

if TYPE_CHECKING:
    import pandas as pd

    from labrunner.calibration.fit import FitOptions, FitResult
    from labrunner.data_source import CampaignData
    from labrunner.discrepancy.diagnose import Diagnosis
    from labrunner.store_address import StoreAddress

log = logging.getLogger(__name__)


def read_campaign_csv(path: str | Path) -> pd.DataFrame:
    """A campaign CSV, validated (errors name the file, line and column)."""
    from labrunner.campaign_csv import read_campaign

    return read_campaign(path)


def load_data(data: str | Path | StoreAddress, *, campaign: int | None = None,
              include_monitor: bool = False) -> CampaignData:
    """Validated campaign rows (campaign CSV columns) with provenance, from a CSV or a store."""
    from labrunner.data_source import load_campaign_data

    return load_campaign_data(data, campaign, include_monitor=include_monitor)


def fit(data: str | Path | StoreAddress | CampaignData, *, campaign: int | None = None,
        options: FitOptions | None = None, save: bool = True, out: str | Path | None = None, force: bool = False,
        progress: Callable[[str], None] | None = None, **overrides: Any) -> FitResult:
    """Fit the calibration models to a campaign (a store's campaign, or a campaign CSV): what
    `labrunner fit` computes. `options` (a `labrunner.calibration.FitOptions`) and `overrides`
    (its fields: `poly_order`, `poly_method`, `rbf_variants`, `rbf_export`, `evaluate`, `splits`,
    `seed`, ...) say what to fit. With a store and `save`, the fit is stored in it with its
    provenance; with `out`, the model files are written there (a directory that is not empty only
    with `force`; never one holding the data). `progress` gets messages."""
    import dataclasses

    from labrunner.calibration.fit import FitOptions, fit_campaign
    from labrunner.data_source import CampaignData

    try:
        opts = dataclasses.replace(options or FitOptions(), **overrides)
    except TypeError as exc:
        raise UserError(f"fit options: {exc}") from None
    if out is not None:  # before the work and before the fit is stored: a refusal changes nothing
        source, is_store = _source(data)
        check_output(out, store=source if is_store else None, inputs=[source], force=force, directory=True,
                     option="out")
    address: str | Path | StoreAddress | None
    if isinstance(data, CampaignData):
        prov, address = data.provenance, data.store
        result = fit_campaign(data.frame, opts, provenance=prov, progress=progress)
    else:
        from labrunner.calibration.fit_rows import campaign_rows

        # A store's campaign is read in chunks (the fit keeps record summaries and bounded row sets).
        prov, rows = campaign_rows(data, campaign)
        address = data if prov.get("kind") == "store" else None
        result = fit_campaign(rows, opts, provenance=prov, progress=progress)
    if save and prov.get("kind") == "store":
        from labrunner.store import Store

        # The address read (a URL's password included); the provenance shows it masked.
        with Store.open_existing(address or prov["source"]) as store:
            fit_id = store.save_fit(int(prov["campaign_id"]), result.to_dict(), result.provenance)
        log.info("fit %d stored in %s (campaign %s)", fit_id, prov["source"], prov["campaign_id"])
        if progress is not None:
            where = prov["source"] if isinstance(data, CampaignData) else data
            progress(f"fit {fit_id} stored in {where} (campaign {prov['campaign_id']})")
    if out is not None:
        write_fit(result, out, force=force)
    return result


def _source(data: str | Path | StoreAddress | CampaignData) -> tuple[str | Path | StoreAddress | None, bool]:
    """Where a fit's data come from, and whether that is a store (for `check_output`)."""
    from labrunner.data_source import CampaignData
    from labrunner.store_address import is_store

    if isinstance(data, CampaignData):
        return data.store or data.provenance.get("source"), data.provenance.get("kind") == "store"
    # The header is read only when handed a path, before this call opens anything of it.
    return data, is_store(data)


def write_fit(result: FitResult, out: str | Path, summary: str | None = None, *, force: bool = False) -> list[str]:
    """Write a fit's model JSON files, C header, summary and evaluation tables into `out`; returns the names.
    `out` may not hold the fitted data; a directory that is not empty is written into only with `force`."""
    from labrunner.calibration.outputs import write_outputs

    prov = result.provenance
    check_output(out, store=prov.get("source") if prov.get("kind") == "store" else None, inputs=[prov.get("source")],
                 force=force, directory=True, option="out")
    return write_outputs(result, Path(out), summary)


def diagnose(data: str | Path | StoreAddress | CampaignData | pd.DataFrame, *, campaign: int | None = None,
             **options: Any) -> Diagnosis:
    """What the simulated IMU model gets wrong in measured data (a store's campaign with its monitor
    rows, a campaign CSV, or a frame): what `labrunner diagnose` computes. `options` are
    `labrunner.discrepancy.DiagnoseOptions` fields (`min_evidence`, `causes`, ...)."""
    import pandas as pd

    from labrunner.data_source import CampaignData
    from labrunner.discrepancy.diagnose import DiagnoseOptions
    from labrunner.discrepancy.diagnose import diagnose as run_diagnosis
    from labrunner.discrepancy.measurements import Measurements
    from labrunner.discrepancy.summary import read_store_summary
    from labrunner.store_address import is_store

    try:
        opts = DiagnoseOptions(**options)
    except TypeError as exc:
        raise UserError(f"diagnose options: {exc}") from None
    if isinstance(data, pd.DataFrame):
        frame = data
    elif not isinstance(data, CampaignData) and is_store(data):
        # A store is read block by block into 1 s summaries, as `labrunner diagnose DB` does: bounded
        # memory (0.9 GB for the paper campaign against 12 GB for its full frame; docs/diagnosis.md).
        stored = read_store_summary(data, campaign)
        meas = Measurements.from_frame(stored.frame, stored.summary)
        del stored
        return run_diagnosis(meas, opts)
    else:
        # Ramps and soaks too: thermal lag and hysteresis show there.
        frame = (data if isinstance(data, CampaignData) else load_data(data, campaign=campaign,
                                                                       include_monitor=True)).frame
    return run_diagnosis(frame, opts)
