"""The calibration part of the report: the campaign's latest stored fit, redrawn.

The store keeps a fit as its result JSON (models, per-step calibration, evaluation statistics) but
not the rows and records the figures are drawn from. Re-running the fit with the stored options on
the same rows is cheap (about 1 s for the quick campaign; deterministic for a given seed) and gives
back a whole `FitResult`, so the report draws the figures and prints the tables with the very
functions `labrunner fit` uses, instead of a second, JSON-fed copy of them. The refit is checked
against the stored models; a mismatch is said in the report, not hidden.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import select

from labrunner.calibration.figures import write_figures
from labrunner.calibration.fit import FitOptions, FitResult, fit_campaign
from labrunner.calibration.headline import Headline, headline
from labrunner.calibration.rbf_model import RbfOptions
from labrunner.calibration.records import RecordOptions
from labrunner.calibration.report import headline_lines, summary_markdown
from labrunner.store import Store, fits

from .html import esc, image, markdown, note


@dataclass
class StoredFit:
    """One row of the store's `fits` table, decoded."""

    fit_id: int
    created_wall: float
    software_version: str
    provenance: dict[str, Any]
    result: dict[str, Any]


@dataclass
class FitSection:
    """What the report shows of the fit: the HTML and the headline (None without a fit)."""

    html: str
    headline: Headline | None = None
    result: FitResult | None = None
    stored: StoredFit | None = None
    figures: dict[str, str] = field(default_factory=dict)  # file name -> what it shows
    skipped: dict[str, str] = field(default_factory=dict)  # file name -> why not drawn


def latest_fit(store: Store, campaign_id: int) -> StoredFit | None:
    # The store's fits_frame leaves out the result JSON (it is large); the report needs it.
    q = (select(fits.c.id, fits.c.created_wall, fits.c.software_version, fits.c.provenance, fits.c.result)
         .where(fits.c.campaign_id == campaign_id).order_by(fits.c.id.desc()).limit(1))
    with store.reading() as conn:
        row = conn.execute(q).first()
    if row is None:
        return None
    return StoredFit(int(row.id), float(row.created_wall), str(row.software_version), json.loads(row.provenance),
                     json.loads(row.result))


def options_from_dict(d: dict[str, Any]) -> FitOptions:
    """The stored `options` of a fit back as `FitOptions` (unknown keys, from another version, dropped)."""
    def known(cls: type, values: dict[str, Any]) -> dict[str, Any]:
        names = {f.name for f in fields(cls)}
        return {k: v for k, v in values.items() if k in names}

    top = known(FitOptions, d)
    rbf = known(RbfOptions, dict(top.pop("rbf", {}) or {}))
    if "widths" in rbf:
        rbf["widths"] = tuple(rbf["widths"])
    rec = known(RecordOptions, dict(top.pop("records", {}) or {}))
    for key in ("rbf_variants", "splits"):
        if key in top:
            top[key] = tuple(top[key])
    return FitOptions(**top, rbf=RbfOptions(**rbf), records=RecordOptions(**rec))


def _same_models(result: FitResult, stored: dict[str, Any]) -> bool:
    a = json.dumps(result.to_dict()["models"], sort_keys=True)
    b = json.dumps(stored.get("models"), sort_keys=True)
    if a == b:
        return True
    # Floats of a refit on another machine may differ in the last bits; compare numerically.
    try:
        return bool(np.allclose(_numbers(json.loads(a)), _numbers(json.loads(b)), rtol=1e-6, atol=1e-12))
    except ValueError:
        return False


def _numbers(o: Any) -> list[float]:
    if isinstance(o, dict):
        return [x for k in sorted(o) for x in _numbers(o[k])]
    if isinstance(o, list):
        return [x for v in o for x in _numbers(v)]
    if isinstance(o, bool) or o is None:
        return []
    return [float(o)] if isinstance(o, int | float) else []


def refit(store: Store, campaign_id: int, stored: StoredFit) -> tuple[FitResult, list[str]]:
    """The stored fit computed again on the rows it was made from; notes on anything that differs."""
    data = store.campaign_data(campaign_id)
    frame = data.frame
    notes: list[str] = []
    t_range = stored.provenance.get("t_range_s")
    if isinstance(t_range, list) and len(t_range) == 2:
        # The campaign may have recorded more since (a fit of a paused campaign, then resumed).
        frame = frame[(frame.t_s >= t_range[0]) & (frame.t_s <= t_range[1])]
    if stored.provenance.get("rows") not in (None, len(frame)):
        notes.append(f"the stored fit was made from {stored.provenance.get('rows'):,} rows, the store now holds "
                     f"{len(frame):,} in its time range; figures are drawn from these")
    provenance = {**stored.provenance}
    result = fit_campaign(frame.reset_index(drop=True), options_from_dict(stored.result.get("options", {})),
                          provenance=provenance)
    if not _same_models(result, stored.result):
        notes.append(f"redrawing the fit with this labrunner gives models that differ from the stored ones (fitted "
                     f"with {stored.software_version}); the figures and tables are of the refit")
    return result, notes


def _figure_html(result: FitResult) -> tuple[str, dict[str, str], dict[str, str]]:
    import base64

    parts: list[str] = []
    with tempfile.TemporaryDirectory(prefix="labrunner-report-") as tmp:
        drawn = write_figures(result, Path(tmp))
        for name, what in drawn.written.items():
            uri = "data:image/png;base64," + base64.b64encode((Path(tmp) / name).read_bytes()).decode("ascii")
            parts.append(image(uri, what, f"{name}: {what}", f"fig-{name.removesuffix('.png')}"))
    parts += [note(f"not drawn: {name}: {why}") for name, why in drawn.skipped.items()]
    return "\n".join(parts), drawn.written, drawn.skipped


def fit_section(store: Store, campaign_id: int, *, status: str, fit_planned: bool) -> FitSection:
    stored = latest_fit(store, campaign_id)
    if stored is None:
        if not fit_planned:
            why = "the procedure turns the end-of-run fit off (fit: {run: false})"
        elif status != "done":
            why = (f"the campaign is {status}: the end-of-run fit runs when it finishes "
                   "(`labrunner resume DB`)")
        else:
            why = "the end-of-run fit did not store a result (see the campaign's events)"
        return FitSection(html=note(f"No fit is stored for this campaign: {why}. `labrunner fit DB` fits what is "
                                    "recorded and stores it; a report written afterwards shows it."))
    result, notes = refit(store, campaign_id, stored)
    figures, written, skipped = _figure_html(result)
    summary = summary_markdown(result)
    body = summary.split("\n", 1)[1] if summary.startswith("# ") else summary  # the section has its heading
    tables = body.split("\n".join(headline_lines(result)), 1)[-1]  # the headline is shown once, at the top
    html_text = "\n".join([
        f"<p class=\"sub\">Fit {stored.fit_id} of this campaign, stored by labrunner {esc(stored.software_version)}"
        f" ({esc(stored.provenance.get('fitted_at', '?'))}); exported models in the campaign's fit directory.</p>",
        *[note(n) for n in notes],
        markdown("\n".join(headline_lines(result))),
        "<h3>Figures</h3>", figures,
        "<h3>Tables</h3>", markdown(tables, heading_offset=1),
    ])
    return FitSection(html=html_text, headline=headline(result), result=result, stored=stored, figures=written,
                      skipped=skipped)
