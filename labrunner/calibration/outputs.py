"""Writes a fit's files: model JSON, the C header, the figures, the summary and the evaluation tables."""

from __future__ import annotations

import logging
from pathlib import Path

from .export import save_model, write_c_header
from .fit import FitResult
from .report import evaluation_csv, summary_markdown

log = logging.getLogger(__name__)


def draw_figures(result: FitResult, out: Path) -> tuple[list[str], str]:
    """The figures (PNG) in `out`: their names and the summary's "Figures" section. Never raises:
    the models are written already and a figure is only a view of them."""
    try:
        from .figures import write_figures  # matplotlib and allantools load only when figures are drawn

        report = write_figures(result, out)
    except Exception as exc:
        log.warning("figures not drawn: %s: %s", type(exc).__name__, exc, exc_info=log.isEnabledFor(logging.DEBUG))
        return [], f"## Figures\n\nNo figures: {type(exc).__name__}: {exc}"
    return list(report.written), report.markdown()


def header_comment(result: FitResult) -> str:
    """The C header's provenance block: software, data, campaign and how complete it was, what was not
    fitted (or only in combination) and why; one item a line."""
    prov = result.provenance
    lines = [f"labrunner {prov.get('software', {}).get('version', '?')}, fitted {prov.get('fitted_at', '?')}",
             f"data: {prov.get('source', '?')}"]
    if prov.get("kind") == "store":
        lines.append(f"campaign {prov.get('campaign_id', '?')} ({prov.get('campaign', '?')}), status "
                     f"{prov.get('status', '?')}: {prov.get('steps_recorded', '?')} of "
                     f"{prov.get('steps_planned', '?')} planned steps recorded")
    else:
        lines.append("campaign CSV: steps planned unknown")
    if result.unfinished:
        lines.append("WARNING: " + result.unfinished)
    lines += [f"not fitted: {s}" for s in result.not_fitted] or ["not fitted: nothing"]
    lines += [f"fitted in combination: {s}" for s in result.combined]
    lines += [f"not exported: {s}" for s in result.not_exported]
    return "\n".join(lines)


def write_fit_files(result: FitResult, out: Path, summary: str | None = None) -> tuple[list[str], str]:
    """Write the model JSON files, the C header, the figures, the summary and the evaluation tables into
    `out`; returns the names written and the figures section appended to summary.md."""
    out.mkdir(parents=True, exist_ok=True)
    prov = result.export_provenance()
    lag = result.temperature_filter  # the models' temperature filter (a thermal lag used), or None
    branch = result.branch_model  # the outputs' branch offset (hysteresis fitted per branch), or None
    save_model(result.polynomial, out / "polynomial.json", prov, lag, branch)
    written = ["polynomial.json"]
    if result.rbf is not None:
        save_model(result.rbf, out / "rbf.json", prov, lag, branch)
        written.append("rbf.json")
    write_c_header(out / "imu_calibration.h", result.polynomial, result.rbf, comment=header_comment(result),
                   temperature_filter=lag, branch=branch)
    figures, section = draw_figures(result, out)
    text = summary if summary is not None else summary_markdown(result)
    (out / "summary.md").write_text(text + "\n\n" + section + "\n")
    (out / "evaluation.csv").write_text(evaluation_csv(result))
    return written + ["imu_calibration.h", "summary.md", "evaluation.csv"] + figures, section


def write_outputs(result: FitResult, out: Path, summary: str | None = None) -> list[str]:
    """Write the model JSON files, the C header, the figures and the evaluation tables into `out`; returns
    the names."""
    return write_fit_files(result, out, summary)[0]
