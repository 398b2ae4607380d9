"""Readable tables of a FitResult: terminal text, Markdown and CSV."""

from __future__ import annotations

import csv
import io

import numpy as np

from .evaluation import SplitResult
from .fit import FitResult
from .headline import Headline, gain_pct, headline, triad_rms
from .ins import InsErrors
from .triads import AXES, CHANNELS, TRIAD_SLICE, UNITS

TRIAD_TITLES = {"accel": "Accelerometer", "gyro": "Gyroscope"}


def _g(v: float, digits: int = 4) -> str:
    if v is None or not np.isfinite(v):
        return "-"
    return f"{v:.{digits}g}"


def _pct(v: float) -> str:
    return "-" if not np.isfinite(v) else f"{v:.2f}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table (also readable as plain text)."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line = lambda r: "| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    return "\n".join([line(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|"] + [line(r) for r in rows])


def paper_table(split: SplitResult, triad: str, rbf_name: str) -> str:
    """The paper's Table 2/3 layout: mean and std of the error per axis, with improvements."""
    sl = TRIAD_SLICE[triad]
    header = [""] + [f"{TRIAD_TITLES[triad]} {a.upper()} {s}" for a in AXES for s in ("mean", "std")]
    rows = []
    for label, name in (("Raw data", "raw"), ("Polynomial", "polynomial"), ("RBF network", rbf_name)):
        if name not in split.samples:
            continue
        st = split.samples[name]
        rows.append([label] + [_g(v) for j in range(3) for v in (st.mean[sl][j], st.std[sl][j])])
        if name != "raw":
            im, isd = split.improvement(name, "mean")[sl], split.improvement(name, "std")[sl]
            rows.append(["Improvement (%)"] + [_pct(v) for j in range(3) for v in (im[j], isd[j])])
    return _table(header, rows)


def rms_table(split: SplitResult) -> str:
    """RMS error of every model per channel: samples / record means."""
    header = ["model"] + [f"{c} ({UNITS[c.split('_')[0]]})" for c in CHANNELS]
    rows = []
    for name, st in split.samples.items():
        rec = split.records[name]
        rows.append([name] + [f"{_g(a, 3)} / {_g(b, 3)}" for a, b in zip(st.rms, rec.rms)])
    return _table(header, rows)


def static_table(split: SplitResult) -> str:
    header = ["model", "mean |a|-1 g", "std |a|", "mean |w| deg/s", "std |w|", "records: rms |a|-1", "records: rms |w|"]
    rows = []
    for name, s in split.static.items():
        if s.n == 0:
            continue
        rows.append([name, _g(s.accel_norm_err_mean), _g(s.accel_norm_err_std), _g(s.gyro_norm_mean),
                     _g(s.gyro_norm_std), _g(s.record_accel_norm_err_rms), _g(s.record_gyro_norm_rms)])
    return _table(header, rows) if rows else "(no static records held out)"


def coefficient_table(result: FitResult, triad: str) -> str:
    tp = result.polynomial.triads()[triad]
    m = tp.order + 1
    header = ["term"] + [f"c{k} (per C^{k})" if k else "c0" for k in range(m)]
    rows = []
    for i in range(3):
        rows.append([f"bias {AXES[i]}"] + [f"{_g(tp.bias[i, k], 5)} ± {_g(tp.bias_std[i, k], 2)}" for k in range(m)])
    for i in range(3):
        for j in range(3):
            name = f"scale {AXES[i]}" if i == j else f"misalign {AXES[i]}{AXES[j]}"
            rows.append([name] + [f"{_g(tp.scale[i, j, k], 5)} ± {_g(tp.scale_std[i, j, k], 2)}" for k in range(m)])
    return _table(header, rows)


def _exported_sentence(result: FitResult, h: Headline) -> str:
    poly = f"the polynomial ({h.polynomial}; `lr_poly_compensate`, polynomial.json)"
    if result.rbf is None:
        return f"**Exported** to the C header imu_calibration.h: {poly}; no RBF network was trained."
    return (f"**Exported** to the C header imu_calibration.h: the RBF network `{h.exported}` "
            f"(`lr_rbf_compensate`, rbf.json) and {poly}.")


def headline_lines(result: FitResult) -> list[str]:
    """The first lines of the summary: the exported model, its held-out gain, what was not fitted."""
    h = headline(result)
    out = [f"**Unfinished campaign:** {result.unfinished}.", ""] if result.unfinished else []
    out += [_exported_sentence(result, h), ""]
    if result.not_exported:
        out += ["**Not exported:** " + "; ".join(result.not_exported) + ".", ""]
    if result.combined:
        out += ["**Fitted in combination:** " + " ".join(s + "." for s in result.combined), ""]
    if h.split is None:
        why = "no evaluation ran (--no-eval)" if not result.evaluation else "every evaluation split was skipped"
        out += [f"**Held-out gain:** not measured: {why}.", ""]
    else:
        out += [f"**Held-out gain** of `{h.exported}` on the `{h.split.name}` split, {h.split.description}; "
                "RMS error of the held-out samples over x, y, z:", ""]
        for triad, g in h.gains.items():
            unit = UNITS[triad]
            line = (f"- {TRIAD_TITLES[triad].lower()}: {_g(g.raw_rms, 3)} {unit} raw -> {_g(g.exported_rms, 3)} "
                    f"{unit}: gain {_pct(g.gain_vs_raw_pct)} % over raw")
            if h.exported != "polynomial":
                line += (f", {_pct(g.gain_vs_polynomial_pct)} % over the polynomial "
                         f"({_g(g.polynomial_rms, 3)} {unit})")
            if g.best_model != h.exported and g.best_rms < 0.99 * g.exported_rms:  # 1 %: not mere noise
                line += f"; lowest on this split: `{g.best_model}` ({_g(g.best_rms, 3)} {unit})"
            out.append(line)
        out.append("")
    if result.not_fitted:
        out += [f"**Not fitted:** {len(result.not_fitted)} item(s): " + "; ".join(result.not_fitted) + ".", ""]
    else:
        out += ["**Not fitted:** nothing; every term and every evaluation split was fitted.", ""]
    return out


def ins_table(ins: dict[str, InsErrors]) -> str:
    """Per model: position and attitude error at the end of the INS windows."""
    rows = [[name, f"{_g(e.position_m, 3)} ({_g(e.position_m_max, 3)})", _g(e.attitude_deg, 3)]
            for name, e in ins.items()]
    return _table(["model", "position error (m)", "attitude error (deg)"], rows)


def gains_table(result: FitResult) -> str:
    """Per model: the largest departure of its gain from the fitted scale, where, and whether it may be exported."""
    rows = []
    for name, g in result.gains.items():
        rows.append([name, f"{100 * g.max_departure:.3g}", f"{g.gain_min:.4f} .. {g.gain_max:.4f}",
                     f"{g.worst_channel} at {g.worst_temp_c:.1f} C", "yes" if g.passed else "no"])
    return _table(["model", "max departure (%)", "diagonal gain / fitted", "worst", "exportable"], rows)


def gain_table(result: FitResult) -> str:
    """Per split that ran and per triad: RMS over x, y, z of raw, polynomial and exported model, with gains."""
    h = headline(result)
    header = ["split", "triad", "raw", "polynomial", h.exported, "px4", "gain over raw (%)",
              "gain over polynomial (%)", "gain over px4 (%)"]
    rows = []
    for split in result.evaluation:
        if split.skipped or "raw" not in split.samples:
            continue
        for triad in TRIAD_TITLES:
            raw = triad_rms(split, "raw", triad)
            poly = triad_rms(split, "polynomial", triad)
            exp = triad_rms(split, h.exported, triad) if h.exported in split.samples else poly
            px4 = triad_rms(split, "px4", triad) if "px4" in split.samples else float("nan")
            rows.append([split.name, f"{triad} ({UNITS[triad]})", _g(raw, 3), _g(poly, 3), _g(exp, 3), _g(px4, 3),
                         _pct(gain_pct(exp, raw)), _pct(gain_pct(exp, poly)), _pct(gain_pct(exp, px4))])
    return _table(header, rows) if rows else "(no evaluation)"


def summary_markdown(result: FitResult) -> str:
    """The whole summary: the headline, data, what could not be fitted, coefficients, evaluation tables."""
    d = result.data_summary
    rbf_name = f"rbf_{result.options.rbf_export}" if result.options.rbf_export else ""
    out = ["# Calibration fit", ""] + headline_lines(result)
    if result.evaluation:
        out += ["## Held-out error at a glance (RMS of sample errors over x, y, z)", "", gain_table(result), ""]
    src = result.provenance.get("source", "data frame")
    out += [f"Data: {src} — {d['rows']:,} rows, {d['records']} records in {len(d['temperature_steps'])} temperature "
            f"steps, orientations {' '.join(d['orientations'])}, IMU temperature "
            f"{d['imu_temp_range_c'][0]:.2f} … {d['imu_temp_range_c'][1]:.2f} C.", ""]
    steps = [[f"{s['temp_c']:.2f}", f"{s['range_c'][0]:.2f} … {s['range_c'][1]:.2f}", str(s["records"]),
              " ".join(s["orientations"])] for s in d["temperature_steps"]]
    out += ["## Temperature steps", "", _table(["T (C)", "record range (C)", "records", "orientations"], steps), ""]
    if result.not_fitted:
        out += ["## Not fitted", ""] + [f"- {s}" for s in result.not_fitted] + [""]
    if result.gains:
        out += ["## Gain of each model (output vs input)", "",
                "The Jacobian of each model's output with respect to its input, by secant differences of "
                "0.05 g and 5 deg/s at training record means, at their temperature and a margin beyond the "
                "training temperatures, relative to the fitted scale (I + S(T))^-1; a model departing by more "
                "than 0.5 % is not exported.", "", gains_table(result), ""]
    if result.notes:
        out += ["## Notes", ""] + [f"- {s}" for s in result.notes] + [""]
    for triad in ("accel", "gyro"):
        tp = result.polynomial.triads()[triad]
        out += [f"## Polynomial model: {TRIAD_TITLES[triad].lower()} ({tp.method}, order {tp.order}, "
                f"coefficients of (T - {tp.t_ref_c:g} C)^k, {UNITS[triad] if triad == 'gyro' else 'g'} "
                f"for bias, unitless for S; ± 1 sigma)", "", coefficient_table(result, triad), ""]
    for split in result.evaluation:
        out += [f"## Evaluation: {split.name}", "", split.description + ".", ""]
        if split.skipped:
            out += [f"Skipped: {split.skipped}.", ""]
            continue
        out += [f"Trained on {split.n_train_records} records at {', '.join(f'{t:g}' for t in split.train_temps_c)} C; "
                f"tested on {split.n_test_rows:,} rows at {', '.join(f'{t:g}' for t in split.test_temps_c)} C.", ""]
        for triad in ("accel", "gyro"):
            out += [f"Error of the {TRIAD_TITLES[triad].lower()} ({UNITS[triad]}), samples "
                    "(layout of the paper's Tables 2-3):", "", paper_table(split, triad, rbf_name), ""]
        out += ["RMS error per model, samples / record means:", "", rms_table(split), ""]
        if split.px4_skipped:
            scope = "not scored" if "px4" not in split.samples else "its rows pass unchanged for"
            out += [f"PX4's method ({scope}): {split.px4_skipped}.", ""]
        out += ["Static check (records without rotation):", "", static_table(split), ""]
        if split.ins:
            n = next(iter(split.ins.values())).n_windows
            out += [f"INS test (the paper's Sec. V.C): strapdown navigation over {n} windows of 60 s of static "
                    "held-out rows; errors at the window's end, mean (max):", "", ins_table(split.ins), ""]
        elif split.ins_skipped:
            out += [f"INS test: not run: {split.ins_skipped}.", ""]
        ex = {k: v for k, v in split.extrapolated_fraction.items() if v > 0}
        if ex:
            out += ["Fraction of held-out rows flagged as extrapolation: "
                    + ", ".join(f"{k} {100 * v:.1f} %" for k, v in ex.items()), ""]
    return "\n".join(out)


def evaluation_csv(result: FitResult) -> str:
    """One row per split x model x channel."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["split", "model", "channel", "mean", "std", "rms", "record_rms", "improvement_mean_pct",
                "improvement_std_pct", "extrapolated_fraction"])
    for split in result.evaluation:
        if split.skipped:
            continue
        for name, st in split.samples.items():
            im = split.improvement(name, "mean") if name != "raw" else np.full(6, np.nan)
            isd = split.improvement(name, "std") if name != "raw" else np.full(6, np.nan)
            for j, ch in enumerate(CHANNELS):
                w.writerow([split.name, name, ch, f"{st.mean[j]:.9g}", f"{st.std[j]:.9g}", f"{st.rms[j]:.9g}",
                            f"{split.records[name].rms[j]:.9g}", f"{im[j]:.4f}", f"{isd[j]:.4f}",
                            f"{split.extrapolated_fraction.get(name, 0.0):.4f}"])
    return buf.getvalue()
