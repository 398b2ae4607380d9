"""`write_report`: one self-contained HTML file of a campaign, read from its store.

Sections in order: headline, overview, steps, events, calibration, diagnosis, provenance. Each works
on what the store holds; one that has no data (a paused campaign's fit, a campaign with no samples
yet) says why instead of disappearing, so a reader knows it was looked for.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pandas as pd

from labrunner.database import Campaign, open_database
from labrunner.output_paths import check_output
from labrunner.version import __version__

from .fit_section import FitSection, fit_section
from .html import FILTER_JS, STYLE, esc, filterable_table, image, note, png_data_uri, table
from .overview import FAULT_KINDS, overview_figure

log = logging.getLogger(__name__)

SECTIONS = ("headline", "overview", "steps", "events", "calibration", "diagnosis", "provenance")
NO_DIAGNOSIS = ("The store keeps no diagnoses: `labrunner diagnose DB --json FILE --report DIR` writes its findings "
                "and residual plots to files, which this report cannot see. Run it for the diagnosis of this "
                "campaign.")


@dataclass
class ReportResult:
    """What `write_report` wrote."""

    path: Path
    campaign_id: int
    status: str
    seconds: float
    sections: tuple[str, ...] = SECTIONS
    explained: dict[str, str] = field(default_factory=dict)  # section -> why it has no data
    figures: list[str] = field(default_factory=list)


def _iso(wall: float) -> str:
    return datetime.fromtimestamp(wall, tz=UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def _hours(t_s: float) -> str:
    return f"{t_s / 3600:.2f} h"


def _card(value: str, label: str, cls: str = "") -> str:
    return f'<div class="card {cls}"><b>{esc(value)}</b><span>{esc(label)}</span></div>'


def _section(key: str, title: str, body: str) -> str:
    return f'<section id="{key}"><h2>{esc(title)}</h2>\n{body}\n</section>'


def _headline(campaign: Campaign, events: pd.DataFrame, steps: pd.DataFrame, fit: FitSection) -> str:
    info = campaign.info
    done = int((steps.status == "done").sum())
    faults = int(events.kind.isin(FAULT_KINDS).sum())
    recoveries = int((events.kind == "recovery").sum())
    cards = [
        _card(info.status, "status", f"status-{info.status}"),
        _card(_hours(info.clock_last - info.clock_t0), "lab time"),
        _card(f"{done}/{len(steps)}", "steps recorded"),
        _card(f"{int(steps.n_samples.fillna(0).sum()):,}", "samples"),
        _card(str(faults), f"faults ({recoveries} recoveries)"),
        _card(str(int((steps.attempts > 1).sum())), "re-recorded steps"),
        _card(info.mode, "mode"),
    ]
    lines = []
    h = fit.headline
    if h is None:
        lines.append('<p class="gain">Calibration: no stored fit (see <a href="#calibration">Calibration</a>).</p>')
    else:
        lines.append(f'<p class="gain">Exported model: <b>{esc(h.exported)}</b> (polynomial {esc(h.polynomial)}).</p>')
        units = {"accel": (1e3, "mg"), "gyro": (1.0, "°/s")}
        for triad, g in h.gains.items():
            k, unit = units[triad]
            lines.append(f'<p class="gain">{"Accelerometer" if triad == "accel" else "Gyroscope"}: held-out RMS '
                         f"{g.raw_rms * k:.3g} {unit} raw → <b>{g.exported_rms * k:.3g} {unit}</b>, gain "
                         f"<b>{g.gain_vs_raw_pct:.1f} %</b> over raw, {g.gain_vs_polynomial_pct:.1f} % over the "
                         f"polynomial ({esc(h.split.name if h.split else '?')} split)</p>")
        if h.split is None:
            lines.append('<p class="gain">Held-out gain: not measured (no evaluation split ran).</p>')
    stopped = events[events.kind.isin(("warning", *FAULT_KINDS))].tail(1)
    if info.status in ("paused", "aborted", "failed") and not stopped.empty:
        lines.append(note(f"Last warning or fault: {stopped.message.iloc[0]}"))
    return (f"<h1>Campaign {campaign.id} '{esc(info.name)}' — {esc(info.status)}</h1>"
            f'<p class="sub">{esc(campaign.db.path)} · created {_iso(info.created_wall)} · report '
            f"{_iso(time.time())}</p>" + f'<div class="cards">{"".join(cards)}</div>' + "".join(lines))


def _overview(campaign: Campaign, events: pd.DataFrame, steps: pd.DataFrame) -> tuple[str, str | None]:
    samples = campaign.samples(include_monitor=True)
    if samples.empty:
        why = "no samples recorded yet: the campaign stopped before its first record or monitor stretch"
        return note(f"No overview: {why}."), why
    info = campaign.info
    title = (f"Campaign {campaign.id} '{info.name}': {_hours(info.clock_last - info.clock_t0)} of lab time, "
             f"IMU {np.nanmin(samples.imu_temp_c):.1f} … {np.nanmax(samples.imu_temp_c):.1f} °C")
    fig = overview_figure(samples, events, steps, title)
    caption = ("Chamber air (blue) and IMU (red) temperature with the setpoint (dashed); shaded: soak (green), "
               "remount at the remount temperature (violet), pause (red); violet lines: an orientation mounted; "
               "red dotted lines: faults. Below: the commanded rate of every record step and the measured "
               f"table rate. {len(samples):,} rows (records and 1 s monitor means), decimated for drawing.")
    return image(png_data_uri(fig, dpi=90), "campaign overview", caption, "fig-overview"), None


def _cell(value: object, spec: str = "") -> str:
    """A table cell: empty for a missing value (a step not recorded yet), else formatted."""
    if value is None or pd.isna(value):
        return ""
    return format(int(value) if spec == "d" else value, spec)  # type: ignore[call-overload]


def _steps_table(steps: pd.DataFrame) -> str:
    rows = [[int(r.idx), r.orientation, f"{r.temperature_c:g}", f"{r.rate_dps:g}", r.status, int(r.attempts),
             _cell(r.t_start / 3600 if not pd.isna(r.t_start) else None, ".3f"), _cell(r.n_samples, "d"),
             _cell(r.dropped, "d"), _cell(r.corrupt, "d"), _cell(r.chamber_c, ".2f"), _cell(r.imu_temp_c, ".2f")]
            for r in steps.itertuples()]
    header = ["step", "orientation", "T (°C)", "rate (°/s)", "status", "attempts", "start (h)", "samples",
              "dropped", "corrupt", "chamber (°C)", "IMU (°C)"]
    return filterable_table(header, rows, "steps-table", "filter steps: x_up, planned, -10 …")


def _events_table(events: pd.DataFrame) -> str:
    rows = [[f"{r.t_s / 3600:.3f}", r.kind, _cell(r.state), _cell(r.step_idx, "d"), r.message]
            for r in events.itertuples()]
    counts = events.kind.value_counts().to_dict()
    summary = ", ".join(f"{k} {v}" for k, v in counts.items())
    return (f"<p>{len(events)} events: {esc(summary)}.</p>"
            + filterable_table(["lab time (h)", "kind", "state", "step", "message"], rows, "events-table",
                               "filter events: fault, soaked, paused …"))


def _provenance(campaign: Campaign, fit: FitSection) -> str:
    info = campaign.info
    rows: list[list[object]] = [
        ["store", str(campaign.db.path.resolve())], ["campaign", f"{campaign.id} '{info.name}'"],
        ["created", _iso(info.created_wall)], ["last update", _iso(info.updated_wall)],
        ["recorded with", f"labrunner {info.software_version}"], ["report written by", f"labrunner {__version__}"],
        ["procedure", info.procedure_path or "(text stored with the campaign)"],
        ["procedure SHA-256", info.procedure_sha256], ["mode", info.mode],
        ["sim configuration", "" if info.sim_config is None else str(info.sim_config)],
    ]
    if fit.stored is not None:
        rows += [["fit", f"{fit.stored.fit_id}, stored {_iso(fit.stored.created_wall)} by labrunner "
                         f"{fit.stored.software_version}"],
                 ["fit data", f"{fit.stored.provenance.get('rows', '?'):,} rows, lab time "
                              f"{fit.stored.provenance.get('t_range_s', '?')} s"]]
    return table(["", ""], rows)


def render(campaign: Campaign) -> tuple[str, dict[str, str], list[str]]:
    """The report's HTML, the sections without data (and why), and the figures shown."""
    info = campaign.info
    events = campaign.events()
    steps = campaign.steps()
    explained: dict[str, str] = {}
    fit = fit_section(campaign.db.store, campaign.id, status=info.status,
                      fit_planned=campaign.procedure().model.fit.run)
    if fit.headline is None:
        explained["calibration"] = "no stored fit"
    overview, why = _overview(campaign, events, steps)
    if why:
        explained["overview"] = why
    if events.empty:
        explained["events"] = "no events"
    explained["diagnosis"] = "the store keeps no diagnoses"
    nav = "".join(f'<a href="#{s}">{s}</a>' for s in SECTIONS[1:])
    body = [
        f'<section id="headline">{_headline(campaign, events, steps, fit)}<nav>{nav}</nav></section>',
        _section("overview", "Campaign overview", overview),
        _section("steps", f"Steps ({int((steps.status == 'done').sum())} of {len(steps)} recorded)",
                 _steps_table(steps)),
        _section("events", "Events", _events_table(events) if not events.empty else note("No events stored.")),
        _section("calibration", "Calibration", fit.html),
        _section("diagnosis", "Diagnosis", note(NO_DIAGNOSIS)),
        _section("provenance", "Provenance", _provenance(campaign, fit)),
    ]
    doc = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
           f"<title>labrunner report: campaign {campaign.id} {esc(info.name)}</title>"
           f"<style>{STYLE}</style><script>{FILTER_JS}</script></head><body>\n" + "\n".join(body)
           + "\n</body></html>\n")
    figures = ["overview"] * (why is None) + list(fit.figures)
    return doc, explained, figures


def write_report(db: str | Path, html: str | Path, *, campaign: int | None = None, force: bool = False) -> ReportResult:
    """Write the HTML report of a campaign (default: the latest in `db`) to `html`.

    `html` may not be the store or one of its SQLite files, and an existing file is overwritten only
    with `force` (checked before anything is read)."""
    t0 = time.perf_counter()
    out = check_output(html, store=db, force=force, option="--html")
    assert out is not None  # no stdout: the report is a file a browser opens
    with open_database(db) as database:
        chosen = database.campaign(campaign)
        doc, explained, figures = render(chosen)
        status = chosen.status
    out.write_text(doc, encoding="utf-8")
    seconds = time.perf_counter() - t0
    log.info("report of campaign %d written to %s in %.1f s", chosen.id, out, seconds)
    return ReportResult(path=out, campaign_id=chosen.id, status=status, seconds=seconds, explained=explained,
                        figures=figures)
