"""The fit at the end of a campaign: read the store, fit, store the fit with provenance, write the models."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from labrunner.store import Store


def fit_and_store(store: Store, campaign_id: int, fit_cfg: Any, out_dir: str | Path | None) -> str:
    """Fit the campaign's records; returns the summary text."""
    from labrunner.calibration.outputs import write_outputs
    from labrunner.calibration.fit import FitOptions, fit_campaign
    from labrunner.calibration.report import summary_markdown

    data = store.campaign_data(campaign_id)
    options = FitOptions(poly_order=fit_cfg.polynomial_order, rbf_variants=FitOptions().rbf_variants if fit_cfg.rbf else (),
                         rbf_export=FitOptions().rbf_export if fit_cfg.rbf else "")
    result = fit_campaign(data.frame, options, provenance=data.provenance)
    store.save_fit(campaign_id, result.to_dict(), result.provenance)
    text = summary_markdown(result)
    if out_dir is not None:
        write_outputs(result, Path(out_dir), text)
    return text

