"""The fit at the end of a campaign: read the store, fit, store the fit with provenance, write the models.

The fit is stored once per campaign's data: a campaign killed after its fit was stored and before it
was marked done fits again on resume (to write the models and the summary), but finds its stored fit
of the same data and does not store a second one.
"""

from __future__ import annotations

import logging
from pathlib import Path

from labrunner.procedure import Fit
from labrunner.store import Store

log = logging.getLogger(__name__)

# Provenance that names the data an end-of-run fit was made from: the same campaign, procedure, rows and
# time range is the same data (recorded steps never change once committed).
SAME_DATA_KEYS = ("kind", "campaign_id", "procedure_sha256", "rows", "t_range_s", "end_of_run")


def fit_and_store(store: Store, campaign_id: int, fit_cfg: Fit, out_dir: str | Path | None) -> str:
    """Fit the campaign's records as the procedure's `fit` section says; returns the summary text."""
    # Imported here: the calibration stack (scipy, matplotlib) is only needed once a campaign ends.
    from labrunner.calibration.fit import FitOptions, fit_campaign
    from labrunner.calibration.fit_rows import campaign_rows
    from labrunner.calibration.outputs import write_fit_files
    from labrunner.calibration.report import summary_markdown

    # Read in chunks through a second connection: the fit keeps record summaries, not the campaign's rows.
    data_provenance, rows = campaign_rows(store.path, campaign_id)
    provenance = {**data_provenance, "end_of_run": True}
    defaults = FitOptions()
    options = FitOptions(poly_order=fit_cfg.polynomial_order, rbf_variants=defaults.rbf_variants if fit_cfg.rbf else (),
                         rbf_export=defaults.rbf_export if fit_cfg.rbf else "", thermal_lag_s=fit_cfg.thermal_lag)
    result = fit_campaign(rows, options, provenance=provenance)
    stored = store.find_fit(campaign_id, provenance, SAME_DATA_KEYS)
    if stored is None:
        store.save_fit(campaign_id, result.to_dict(), result.provenance)
        log.info("campaign %d: fit stored", campaign_id)
    else:
        log.info("campaign %d: the fit of these data is stored already (fit %d)", campaign_id, stored)
    text = summary_markdown(result)
    if out_dir is not None:
        # The figures' section (what was drawn, what was not and why) ends the summary on the terminal too.
        _, figures = write_fit_files(result, Path(out_dir), text)
        text += "\n\n" + figures
    return text
