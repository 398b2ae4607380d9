"""The fit at the end of a campaign: read the store, fit, store the fit with provenance, write the models."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from labrunner.store import Store


def fit_and_store(store: Store, campaign_id: int, fit_cfg: Any, out_dir: str | Path | None) -> str:
    """Fit the campaign's records; returns the summary text."""
    from labrunner.calibration.command import write_outputs
    from labrunner.calibration.fit import FitOptions, fit_campaign
    from labrunner.calibration.report import summary_markdown

    data = store.campaign_data(campaign_id)
    options = FitOptions(poly_order=fit_cfg.polynomial_order, rbf_variants=FitOptions().rbf_variants if fit_cfg.rbf else (),
                         rbf_export=FitOptions().rbf_export if fit_cfg.rbf else "")
    result = fit_campaign(data.frame, options, provenance=data.provenance)
    payload = json.loads(json.dumps(result.to_dict(), allow_nan=False, default=_jsonable))
    store.save_fit(campaign_id, payload, result.provenance)
    text = summary_markdown(result)
    if out_dir is not None:
        write_outputs(result, Path(out_dir), text)
    return text


def _jsonable(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
