"""The report directory: residual plots (PNG), the residual table (CSV) and a Markdown summary."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from labrunner.domain import CHANNELS, ORIENTATIONS

if TYPE_CHECKING:
    from .diagnose import Diagnosis

_MAX_POINTS = 20000  # per scatter panel; more only blurs
_UNITS = {c: ("mg" if c.startswith("accel") else "deg/s") for c in CHANNELS}
_SCALE = {c: (1000.0 if c.startswith("accel") else 1.0) for c in CHANNELS}

# Each plot: file name, x column, x label, what a cause looks like in it.
PLOTS: tuple[tuple[str, str, str, str], ...] = (
    ("residual_vs_temperature.png", "imu_temp_c", "IMU temperature (degC)",
     "non-cubic temperature dependence; heating and cooling apart = hysteresis"),
    ("residual_vs_temperature_rate.png", "temp_rate_c_per_min", "dT/dt (degC/min)", "a slope = thermal lag"),
    ("residual_vs_time_since_power_on.png", "t_on_s", "time since power-on (s)", "a decay = warm-up"),
    ("residual_vs_table_rate.png", "table_rate_dps", "table rate (deg/s)",
     "a parabola = scale non-linearity (gyro) or lever arm (accelerometer)"),
    ("residual_vs_time.png", "t_s", "time since campaign start (h)", "wandering = drift; steps at power-on"),
)


def write_report(diagnosis: Diagnosis, directory: str | Path) -> list[Path]:
    """Write plots, residuals.csv and summary.md into `directory`; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    table = diagnosis.residuals
    written: list[Path] = []
    for name, column, label, _ in PLOTS:
        written.append(_scatter(table, column, label, out / name))
    written.append(_per_group(table, "run", "run (power-on)", out / "residual_by_run.png"))
    written.append(_per_group(table, "orientation", "orientation (specific force)",
                              out / "residual_by_orientation.png"))
    written.append(_gain_plot(diagnosis, out / "heldout_rms.png"))
    csv = out / "residuals.csv"
    table.to_csv(csv, index=False, float_format="%.9g")
    written.append(csv)
    summary = out / "summary.md"
    summary.write_text(summary_markdown(diagnosis, [p.name for p in written if p.suffix == ".png"]))
    written.append(summary)
    return written


def _subsample(table: pd.DataFrame) -> pd.DataFrame:
    if len(table) <= _MAX_POINTS:
        return table
    return table.iloc[np.linspace(0, len(table) - 1, _MAX_POINTS).astype(int)]


def _scatter(table: pd.DataFrame, column: str, label: str, path: Path) -> Path:
    import matplotlib.pyplot as plt

    data = _subsample(table)
    x = data[column].to_numpy(dtype=float)
    if column == "t_s":
        x = x / 3600.0
    fig, axes = plt.subplots(2, 3, figsize=(14, 7), sharex=True)
    branch = data["branch"].to_numpy()
    for ax, c in zip(axes.flat, CHANNELS):
        y = data[f"residual_{c}"].to_numpy() * _SCALE[c]
        y_after = data[f"after_{c}"].to_numpy() * _SCALE[c]
        if column == "imu_temp_c":
            for value, colour, text in ((1, "tab:red", "heating"), (-1, "tab:blue", "cooling"), (0, "0.6", "steady")):
                sel = branch == value
                ax.scatter(x[sel], y[sel], s=2, c=colour, alpha=0.5, label=text, rasterized=True)
        else:
            ax.scatter(x, y, s=2, c="tab:red", alpha=0.5, label="baseline model", rasterized=True)
        ax.scatter(x, y_after, s=1, c="k", alpha=0.3, label="extended model", rasterized=True)
        ax.set_title(c)
        ax.set_ylabel(f"measured - model ({_UNITS[c]})")
        if column == "t_on_s" and np.nanmax(x) > 0:
            ax.set_xscale("symlog", linthresh=60.0)
    for ax in axes[-1]:
        ax.set_xlabel(label)
    axes.flat[0].legend(loc="best", fontsize=7, markerscale=4)
    fig.suptitle(f"Residual against {label}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _per_group(table: pd.DataFrame, column: str, label: str, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(14, 7), sharex=True)
    groups = table.groupby(column, observed=True)
    for ax, c in zip(axes.flat, CHANNELS):
        weights = table["rows"]
        for key, values in (("residual", "tab:red"), ("after", "k")):
            col = f"{key}_{c}"
            mean = (table[col] * weights).groupby(table[column], observed=True).sum() / groups["rows"].sum()
            xs = [ORIENTATIONS.index(k) if column == "orientation" else k for k in mean.index]
            ax.plot(xs, mean.to_numpy() * _SCALE[c], "o-", c=values, ms=3,
                    label="baseline model" if key == "residual" else "extended model")
        ax.set_title(c)
        ax.set_ylabel(f"mean residual ({_UNITS[c]})")
        if column == "orientation":
            ax.set_xticks(range(len(ORIENTATIONS)), ORIENTATIONS, rotation=45)
    for ax in axes[-1]:
        ax.set_xlabel(label)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"Mean residual per {label}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _gain_plot(diagnosis: Diagnosis, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, triad in zip(axes, ("accel", "gyro")):
        chans = [c for c in CHANNELS if c.startswith(triad)]
        before = [diagnosis.gain.heldout_rms_before[c] * _SCALE[c] for c in chans]
        after = [diagnosis.gain.heldout_rms_after[c] * _SCALE[c] for c in chans]
        xs = np.arange(len(chans))
        ax.bar(xs - 0.2, before, 0.4, label="baseline model", color="tab:red")
        ax.bar(xs + 0.2, after, 0.4, label="extended model", color="k")
        ax.set_xticks(xs, chans)
        ax.set_ylabel(f"held-out RMS ({_UNITS[chans[0]]})")
    axes[0].legend(fontsize=8)
    fig.suptitle("Held-out residual RMS (time blocks held out)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def summary_markdown(diagnosis: Diagnosis, plots: list[str]) -> str:
    lines = ["# Diagnosis: what the simulated IMU gets wrong", "",
             f"**Verdict: {diagnosis.verdict}**", ""]
    if diagnosis.findings:
        lines += ["| cause | status | channels | parameters | held-out RMS gain | confounded with |",
                  "|---|---|---|---|---|---|"]
        for f in diagnosis.findings:
            lines.append(f"| {f.cause} | {f.status} | {', '.join(f.channels)} "
                         f"| `{_compact(f.to_json()['parameters'])}` "
                         f"| {f.gain.improvement_pct:.1f} % | {', '.join(f.confounded_with) or '-'} |")
        lines.append("")
        for f in diagnosis.findings:
            lines += [f"- **{f.cause}**: {f.evidence}"]
        lines.append("")
    else:
        lines += [("No candidate cause earns its parameters on held-out data: the baseline model "
                   "(Eq. 1 with cubic thermal terms) explains the measurements to their noise and drift."), ""]
    lines += ["## Held-out residual RMS per channel", "", "| channel | baseline | extended | gain |",
              "|---|---|---|---|"]
    for c in CHANNELS:
        b, a = diagnosis.gain.heldout_rms_before[c], diagnosis.gain.heldout_rms_after[c]
        lines.append(f"| {c} | {b * _SCALE[c]:.4g} {_UNITS[c]} | {a * _SCALE[c]:.4g} {_UNITS[c]} "
                     f"| {diagnosis.gain.improvement_by_channel[c]:.1f} % |")
    lines += ["", "## Not identifiable from this data", ""]
    lines += [f"- {m}" for m in diagnosis.not_identifiable] or ["- (everything the candidates need is covered)"]
    if diagnosis.coverage.notes:
        lines += ["", "## Notes on the data", ""] + [f"- {n}" for n in diagnosis.coverage.notes]
    lines += ["", "## Noise", "", "| channel | white RMS per row | drift per sqrt(s) |", "|---|---|---|"]
    for c, n in diagnosis.noise.items():
        drift = f"{n.drift_per_sqrt_s * _SCALE[c]:.3g} {_UNITS[c]}" if n.drift_evidence > 10 else "none detected"
        lines.append(f"| {c} | {n.white_rms * _SCALE[c]:.3g} {_UNITS[c]} | {drift} |")
    if diagnosis.model_path:
        model = Path(diagnosis.model_path).resolve()
        lines += ["", (f"Extended simulation model: `{diagnosis.model_path}`. To rehearse with it, write "
                       f"`imu_model: {model}` into a sim configuration (say `sim.yaml`) and run "
                       "`labrunner run PROCEDURE --sim --sim-config sim.yaml --db DB`.")]
    lines += ["", "## Plots", ""] + [f"- ![{p}]({p})" for p in plots]
    lines += ["", (f"Method: {diagnosis.method['criterion']}; {diagnosis.method['folds']} folds of "
                   f"{diagnosis.method['holdout_segment_s']:.0f} s stretches, "
                   f"{diagnosis.method['blocks']} blocks."), ""]
    return "\n".join(lines)


def _compact(value: object) -> str:
    text = str(value).replace("'", "")
    return text if len(text) < 160 else text[:157] + "..."
