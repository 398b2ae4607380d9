"""The report directory: residual plots (PNG), the residual table (CSV) and a Markdown summary."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from labrunner.domain import CHANNELS, ORIENTATIONS

if TYPE_CHECKING:
    from matplotlib.figure import Figure

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


_BASELINE = "tab:red"
_EXTENDED = "k"
_BINS = 40  # binned means of the extended model's residual along x


def write_report(diagnosis: Diagnosis, directory: str | Path) -> list[Path]:
    """Write plots, residuals.csv and summary.md into `directory`; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    table = diagnosis.residuals
    written: list[Path] = []
    for name, column, label, _ in PLOTS:
        written.append(_save(scatter_figure(table, column, label), out / name))
    notes: list[str] = []
    if runs_are_orientations(table):
        # Each run is one orientation: one figure says it all, the other would repeat it.
        written.append(_save(per_group_figure(table, "run", "run (power-on)", with_orientation=True),
                             out / "residual_by_run.png"))
        notes.append("`residual_by_run.png` stands for both run and orientation: each run (power-on) was "
                     "recorded in one orientation and each orientation in one run, so `residual_by_orientation.png` "
                     "would show the same data again and is not drawn.")
    else:
        written.append(_save(per_group_figure(table, "run", "run (power-on)"), out / "residual_by_run.png"))
        written.append(_save(per_group_figure(table, "orientation", "orientation (specific force)"),
                             out / "residual_by_orientation.png"))
    written.append(_save(gain_figure(diagnosis), out / "heldout_rms.png"))
    if diagnosis.allan is not None:
        written.append(_save(allan_figure(diagnosis), out / "allan_deviation.png"))
    csv = out / "residuals.csv"
    table.to_csv(csv, index=False, float_format="%.9g")
    written.append(csv)
    summary = out / "summary.md"
    summary.write_text(summary_markdown(diagnosis, [p.name for p in written if p.suffix == ".png"], notes))
    written.append(summary)
    return written


def runs_are_orientations(table: pd.DataFrame) -> bool:
    """Runs and orientations coincide one-to-one (each run one orientation, each orientation one run)."""
    if table.empty:
        return False
    pairs = table[["run", "orientation"]].drop_duplicates()
    return bool(pairs.run.is_unique and pairs.orientation.is_unique)


def _save(fig: Figure, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _figure_legend(fig: Figure, axes: Any, markerscale: float = 1.0) -> None:
    """One legend for the figure, below the panels (outside every axes, over no data)."""
    handles, labels = [], []
    for ax in np.ravel(axes):
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels:
                handles.append(h)
                labels.append(lab)
    fig.legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, 0.0), ncol=min(len(labels), 6),
               fontsize=9, markerscale=markerscale, frameon=False)


def _subsample(table: pd.DataFrame) -> pd.DataFrame:
    if len(table) <= _MAX_POINTS:
        return table
    return table.iloc[np.linspace(0, len(table) - 1, _MAX_POINTS).astype(int)]


def _binned_mean(x: np.ndarray, y: np.ndarray, log: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Mean of y in bins along x (empty bins left out), for a thin line over the points."""
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size == 0:
        return x, y
    lo, hi = float(x.min()), float(x.max())
    if hi <= lo:
        return np.array([lo]), np.array([float(y.mean())])
    if log and lo >= 0.0:
        edges = np.concatenate([[lo], np.geomspace(max(lo, 1.0), hi, _BINS)])
        edges = np.unique(edges)
    else:
        edges = np.linspace(lo, hi, _BINS + 1)
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    count = np.bincount(idx, minlength=len(edges) - 1)
    keep = count > 0
    xs = np.bincount(idx, weights=x, minlength=len(edges) - 1)[keep] / count[keep]
    ys = np.bincount(idx, weights=y, minlength=len(edges) - 1)[keep] / count[keep]
    return xs, ys


def scatter_figure(table: pd.DataFrame, column: str, label: str) -> Figure:
    """Baseline residual as coloured points; the extended model's as a thin black line of binned means."""
    import matplotlib.pyplot as plt

    data = _subsample(table)
    x = data[column].to_numpy(dtype=float)
    if column == "t_s":
        x = x / 3600.0
    fig, axes = plt.subplots(2, 3, figsize=(14, 7.5), sharex=True)
    branch = data["branch"].to_numpy()
    log = column == "t_on_s" and bool(np.nanmax(x) > 0) if x.size else False
    for ax, c in zip(axes.flat, CHANNELS):
        y = data[f"residual_{c}"].to_numpy() * _SCALE[c]
        y_after = data[f"after_{c}"].to_numpy() * _SCALE[c]
        if column == "imu_temp_c":
            for value, colour, text in ((1, "tab:red", "heating"), (-1, "tab:blue", "cooling"), (0, "0.6", "steady")):
                sel = branch == value
                ax.scatter(x[sel], y[sel], s=3, c=colour, alpha=0.5, label=f"baseline model, {text}",
                           rasterized=True, zorder=1)
            # Hysteresis shows as heating and cooling apart: the extended model's means per branch.
            for value, style, text in ((1, "-", "heating"), (-1, "--", "cooling")):
                sel = branch == value
                if sel.sum() >= 2:
                    bx, by = _binned_mean(x[sel], y_after[sel])
                    ax.plot(bx, by, style, c=_EXTENDED, lw=1.0, zorder=3,
                            label=f"extended model, binned mean ({text})")
        else:
            ax.scatter(x, y, s=3, c=_BASELINE, alpha=0.5, label="baseline model", rasterized=True, zorder=1)
            bx, by = _binned_mean(x, y_after, log=log)
            ax.plot(bx, by, "-", c=_EXTENDED, lw=1.0, zorder=3, label="extended model, binned mean")
        ax.set_title(c)
        ax.set_ylabel(f"measured - model ({_UNITS[c]})")
        if log:
            ax.set_xscale("symlog", linthresh=60.0)
    for ax in axes[-1]:
        ax.set_xlabel(label)
    fig.suptitle(f"Residual against {label}")
    fig.tight_layout(rect=(0.0, 0.06, 1.0, 1.0))
    _figure_legend(fig, axes, markerscale=4.0)
    return fig


def per_group_figure(table: pd.DataFrame, column: str, label: str, with_orientation: bool = False) -> Figure:
    """Weighted mean residual per run or orientation: baseline as a broad coloured line, the extended model
    as a thin black one on top (both stay visible where they agree). `with_orientation`: runs are
    orientations one-to-one, and the run ticks name them."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(14, 7.5), sharex=True)
    groups = table.groupby(column, observed=True)
    weights = table["rows"]
    for ax, c in zip(axes.flat, CHANNELS):
        for key, colour, lw, ms, text, z in (("residual", _BASELINE, 3.0, 7, "baseline model", 1),
                                              ("after", _EXTENDED, 1.0, 3, "extended model", 3)):
            col = f"{key}_{c}"
            mean = (table[col] * weights).groupby(table[column], observed=True).sum() / groups["rows"].sum()
            xs = [ORIENTATIONS.index(k) if column == "orientation" else k for k in mean.index]
            ax.plot(xs, mean.to_numpy() * _SCALE[c], "o-", c=colour, lw=lw, ms=ms, alpha=0.6 if z == 1 else 1.0,
                    label=text, zorder=z)
        ax.set_title(c)
        ax.set_ylabel(f"mean residual ({_UNITS[c]})")
        if column == "orientation":
            ax.set_xticks(range(len(ORIENTATIONS)), ORIENTATIONS, rotation=45)
        elif with_orientation:
            runs = table[["run", "orientation"]].drop_duplicates().sort_values("run")
            ax.set_xticks(runs.run.tolist(), [f"{r}\n{o}" for r, o in zip(runs.run, runs.orientation)])
    for ax in axes[-1]:
        ax.set_xlabel("run (power-on) and its orientation" if with_orientation else label)
    title = f"Mean residual per {label}"
    if with_orientation:
        title = "Mean residual per run (power-on) = per orientation: each run is one orientation"
    fig.suptitle(title)
    fig.tight_layout(rect=(0.0, 0.06, 1.0, 1.0))
    _figure_legend(fig, axes)
    return fig


def gain_figure(diagnosis: Diagnosis) -> Figure:
    """Held-out RMS per channel, baseline against extended model."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for ax, triad in zip(axes, ("accel", "gyro")):
        chans = [c for c in CHANNELS if c.startswith(triad)]
        before = [diagnosis.gain.heldout_rms_before[c] * _SCALE[c] for c in chans]
        after = [diagnosis.gain.heldout_rms_after[c] * _SCALE[c] for c in chans]
        xs = np.arange(len(chans))
        ax.bar(xs - 0.2, before, 0.4, label="baseline model", color=_BASELINE)
        ax.bar(xs + 0.2, after, 0.4, label="extended model", color=_EXTENDED)
        ax.set_xticks(xs, chans)
        ax.set_ylabel(f"held-out RMS ({_UNITS[chans[0]]})")
    fig.suptitle("Held-out residual RMS (time blocks held out)")
    fig.tight_layout(rect=(0.0, 0.08, 1.0, 1.0))
    _figure_legend(fig, axes)
    return fig


def allan_figure(diagnosis: Diagnosis) -> Figure:
    """Allan deviation of the residuals per channel: measured with its 68 % interval (a band), and the
    simulator's before (white noise only) and after (the fitted noise model), both seen through the same
    fit as the data."""
    import matplotlib.pyplot as plt

    fit = diagnosis.allan
    assert fit is not None
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), sharex=True)
    for i, (ax, c) in enumerate(zip(axes.flat, CHANNELS)):
        k = _SCALE[c]
        if fit.measured.low is not None and fit.measured.high is not None:
            # Drawn first, under the curves: where the band is wider than +-20 % the target meets the
            # measurement's own scatter (few independent differences at the top octaves).
            ax.fill_between(fit.measured.tau_s, fit.measured.low[:, i] * k, fit.measured.high[:, i] * k,
                            color=_BASELINE, alpha=0.3, lw=0, label="measured, 68 % interval (Greenhall EDF)")
        ax.loglog(fit.measured.tau_s, fit.measured.adev[:, i] * k, "o-", color=_BASELINE, label="measured residual")
        ax.loglog(fit.before.tau_s, fit.before.adev[:, i] * k, ":", color="0.5", label="simulator before (white only)")
        ax.loglog(fit.after.tau_s, fit.after.adev[:, i] * k, "-", color=_EXTENDED, lw=1.0,
                  label="simulator after (fitted noise model)")
        ax.set_title(c)
        ax.set_ylabel(f"Allan deviation ({_UNITS[c]})")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("tau (s)")
    fig.suptitle("Allan deviation of measured minus extended model, and of the simulator's noise")
    fig.tight_layout(rect=(0.0, 0.08, 1.0, 1.0))
    _figure_legend(fig, axes)
    return fig


def summary_markdown(diagnosis: Diagnosis, plots: list[str], plot_notes: list[str] | None = None) -> str:
    lines = ["# Diagnosis: what the simulated IMU gets wrong", "",
             f"**Verdict: {diagnosis.verdict}**" + (" (uncertain)" if diagnosis.verdict_uncertain else ""), ""]
    if diagnosis.verdict_note:
        lines += [diagnosis.verdict_note[0].upper() + diagnosis.verdict_note[1:] + ".", ""]
    if diagnosis.findings:
        lines += ["| cause | status | channels | parameters | held-out RMS gain | selected on resamples "
                  "| confounded with |", "|---|---|---|---|---|---|---|"]
        for f in diagnosis.findings:
            share = f"{f.stability.selected_share:.0%}" if f.stability else "-"
            lines.append(f"| {f.cause} | {f.status} | {', '.join(f.channels)} "
                         f"| `{_compact(f.to_json()['parameters'])}` "
                         f"| {f.gain.improvement_pct:.1f} % | {share} | {', '.join(f.confounded_with) or '-'} |")
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
    if diagnosis.allan is not None:
        fit = diagnosis.allan
        lines += ["", "Allan deviation of the residuals (`allan_deviation.png`), the simulator's noise model fitted "
                  "to it: white noise density N (one-sided, per sqrt(Hz); the Allan deviation at 1 s of 1 s rows is "
                  "N / sqrt(2)), bias instability B (Allan floor 0.664 B), rate random walk K (per sqrt(s)); the "
                  "mismatch is the largest relative departure of the simulated Allan deviation over the octaves.",
                  "", "| channel | N | B | K | mismatch before | after |", "|---|---|---|---|---|---|"]
        for c in CHANNELS:
            k, u = _SCALE[c], _UNITS[c]
            lines.append(f"| {c} | {fit.white[c] * k:.3g} {u}/sqrt(Hz) | {fit.bias_instability[c] * k:.3g} {u} "
                         f"| {fit.rate_random_walk[c] * k:.3g} {u}/sqrt(s) | {fit.mismatch_before[c]:.0%} "
                         f"| {fit.mismatch_after[c]:.0%} |")
    if diagnosis.model_path:
        model = Path(diagnosis.model_path).resolve()
        lines += ["", (f"Extended simulation model: `{diagnosis.model_path}`. To rehearse with it, write "
                       f"`imu_model: {model}` into a sim configuration (say `sim.yaml`) and run "
                       "`labrunner run PROCEDURE --sim --sim-config sim.yaml --db DB`.")]
    lines += ["", "## Plots", ""] + [f"- ![{p}]({p})" for p in plots]
    if plot_notes:
        lines += [""] + plot_notes
    lines += ["", (f"Method: {diagnosis.method['criterion']}; {diagnosis.method['folds']} folds of "
                   f"{diagnosis.method['holdout_segment_s']:.0f} s stretches, "
                   f"{diagnosis.method['blocks']} blocks."), ""]
    return "\n".join(lines)


def _compact(value: object) -> str:
    text = str(value).replace("'", "")
    return text if len(text) < 160 else text[:157] + "..."
