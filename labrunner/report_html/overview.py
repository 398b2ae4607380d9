"""The campaign overview figure: chamber air and IMU temperature vs lab time with the setpoints,
soak windows and pauses shaded, the rate schedule below, remounts and faults marked.

Drawn from the store alone (samples with monitor rows, events, steps), so it exists for a campaign
that paused or failed before any fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from labrunner.calibration.figure_style import decimation, headline

MAX_POINTS = 4000  # per curve: a 1180 px wide figure shows no more; drawing 170 k points costs seconds
FAULT_KINDS = ("fault", "interlock")
H = 3600.0


@dataclass(frozen=True)
class Span:
    """A stretch of lab time spent in one sequencer state (hours)."""

    state: str
    start_h: float
    end_h: float


def state_spans(events: pd.DataFrame, end_s: float) -> list[Span]:
    """The stretches between consecutive transitions, each in the state entered (the last until `end_s`)."""
    trans = events[events.kind == "transition"].sort_values(["t_s", "id"], kind="stable")
    t = trans.t_s.to_numpy(dtype=float)
    states = trans.state.astype(str).to_numpy()
    ends = np.append(t[1:], max(end_s, t[-1] if t.size else 0.0))
    return [Span(s, a / H, b / H) for s, a, b in zip(states, t, ends) if b > a]


def _thin(frame: pd.DataFrame) -> pd.DataFrame:
    return frame.iloc[::decimation(len(frame), MAX_POINTS)]


def overview_figure(samples: pd.DataFrame, events: pd.DataFrame, steps: pd.DataFrame, title: str) -> Figure:
    """Temperatures (top) and table rate (bottom) over the campaign; raises ValueError without samples."""
    if samples.empty:
        raise ValueError("no samples recorded yet")
    end_s = float(max(samples.t_s.max(), events.t_s.max() if not events.empty else 0.0))
    fig = Figure(figsize=(12, 6.6))
    axes = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1.4]})
    fig.subplots_adjust(left=0.07, right=0.985, top=0.86, bottom=0.09, hspace=0.08)
    temp_ax, rate_ax = axes
    spans = state_spans(events, end_s)
    shaded = {"soaking": ("#dcefdc", "soak"), "paused": ("#f6c9c9", "paused"), "mounting": ("#e4dcf3", "remount")}
    labelled: set[str] = set()
    for span in spans:
        if span.state in shaded:
            colour, label = shaded[span.state]
            for ax in axes:
                ax.axvspan(span.start_h, span.end_h, color=colour, lw=0,
                           label=label if ax is temp_ax and label not in labelled else None)
            labelled.add(label)

    thin = _thin(samples)
    hours = thin.t_s.to_numpy(dtype=float) / H
    # Setpoint as a step line over every row (not decimated rows only: a short step would vanish).
    sp = samples[["t_s", "setpoint_c"]].dropna()
    sp = sp[sp.setpoint_c.diff().fillna(1.0) != 0]
    if not sp.empty:
        temp_ax.step(np.append(sp.t_s / H, end_s / H), np.append(sp.setpoint_c, sp.setpoint_c.iloc[-1]),
                     where="post", color="#444444", lw=1.2, ls="--", label="setpoint")
    temp_ax.plot(hours, thin.chamber_c.to_numpy(dtype=float), ".", ms=1.5, color="#1f77b4", label="chamber air")
    temp_ax.plot(hours, thin.imu_temp_c.to_numpy(dtype=float), ".", ms=1.5, color="#d62728", label="IMU")
    temp_ax.set_ylabel("temperature (°C)")

    # The records last a minute in a day: drawn as lines they vanish, so one marker per record step.
    done = steps[steps.status == "done"].dropna(subset=["t_start", "t_end"])
    if not done.empty:
        rate_ax.plot((done.t_start + done.t_end) / 2 / H, done.rate_dps, "_", ms=9, mew=2.5, color="#ff7f0e",
                     label="commanded, per record step")
    records = samples[samples.kind == "record"].groupby("step_idx")[["t_s", "table_rate_dps"]].mean()
    if not records.empty:
        rate_ax.plot(records.t_s / H, records.table_rate_dps, ".", ms=3, color="#333333", label="measured mean")
    rate_ax.set_ylabel("table rate (°/s)")
    rate_ax.set_xlabel("lab time (h)")

    mounted = events[(events.kind == "operator") & events.message.str.startswith("IMU mounted")]
    top = temp_ax.get_ylim()[1]
    for t_s, msg in zip(mounted.t_s, mounted.message):
        temp_ax.axvline(t_s / H, color="#6a3d9a", lw=0.8)
        temp_ax.text(t_s / H, top, " " + msg.split()[2].rstrip(","), rotation=90, va="top", ha="left", fontsize=8,
                     color="#6a3d9a")
    faults = events[events.kind.isin(FAULT_KINDS)]
    for ax in axes:
        for t_s in faults.t_s:
            ax.axvline(t_s / H, color="#c62828", lw=1.0, ls=":")
    if not faults.empty:
        temp_ax.plot([], [], color="#c62828", ls=":", label=f"fault ({len(faults)})")
    temp_ax.legend(loc="upper center", bbox_to_anchor=(0.5, 1.13), ncol=8, fontsize=9, markerscale=6,
                   frameon=False)
    rate_ax.legend(loc="lower right", fontsize=8, ncol=2)
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_xlim(0, end_s / H)
    headline(fig, title)
    return fig
