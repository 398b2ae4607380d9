"""Writes a fit's files: model JSON, the C header, the summary and the evaluation tables."""

from __future__ import annotations

from pathlib import Path

from .export import save_model, write_c_header
from .fit import FitResult
from .report import evaluation_csv, summary_markdown


def write_outputs(result: FitResult, out: Path, summary: str | None = None) -> list[str]:
    """Write the model JSON files, the C header and the evaluation tables into `out`; returns the names."""
    out.mkdir(parents=True, exist_ok=True)
    prov = result.provenance
    save_model(result.polynomial, out / "polynomial.json", prov)
    written = ["polynomial.json"]
    if result.rbf is not None:
        save_model(result.rbf, out / "rbf.json", prov)
        written.append("rbf.json")
    comment = (f"labrunner {prov.get('software', {}).get('version', '?')}, data {prov.get('source', '?')}, "
               f"fitted {prov.get('fitted_at', '?')}")
    write_c_header(out / "imu_calibration.h", result.polynomial, result.rbf, comment=comment)
    (out / "summary.md").write_text((summary if summary is not None else summary_markdown(result)) + "\n")
    (out / "evaluation.csv").write_text(evaluation_csv(result))
    return written + ["imu_calibration.h", "summary.md", "evaluation.csv"]
