"""`fit_campaign`: campaign rows in, calibration models, evaluation and provenance out."""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from labrunner.blas_threads import analysis_threads
from labrunner.errors import UserError
from labrunner.version import __version__

from .branch_fit import BranchModel, BranchReport, fit_with_branches
from .evaluation import SPLITS, SplitResult
from .evaluation_chunked import evaluate_chunks
from .fit_rows import CampaignRows, FigureRows, gather_figure_rows, read_records, summary_dict
from .gain import GainCheck, check_models
from .malloc_tuning import tuned_malloc
from .rbf_model import VARIANTS, RbfModel, RbfOptions, train_rbf_models
from .records import RecordOptions, Records, TemperatureSteps, temperature_steps
from .six_position import StepCalibration, calibrate_steps
from .thermal_lag_fit import LagReport, TemperatureFilter, fit_with_lag
from .thermal_poly import PolyModel, TriadPoly, cv_order, fit_joint, fit_two_stage, max_order
from .triads import TRIADS

log = logging.getLogger(__name__)

Progress = Callable[[str], None]


@dataclass(frozen=True)
class FitOptions:
    """What to fit and how. Defaults: cubic joint polynomial, all RBF variants, all splits."""

    poly_order: int | str = 3  # or "cv": chosen per triad by leave-one-step-out cross-validation
    max_poly_order: int = 5  # upper bound for "cv"
    poly_method: str = "joint"  # "joint" (one-stage, default) or "two_stage" (the paper's)
    t_ref_c: float = 25.0
    rbf_variants: tuple[str, ...] = VARIANTS  # networks to train ("paper", "triad", "hybrid")
    rbf_export: str = "hybrid"  # the variant exported as the RBF model (JSON, C header)
    rbf: RbfOptions = field(default_factory=RbfOptions)
    records: RecordOptions = field(default_factory=RecordOptions)
    evaluate: bool = True
    splits: tuple[str, ...] = SPLITS
    holdout_fraction: float = 0.2
    eval_max_rows: int = 1_000_000  # held-out rows scored per split (a random subset beyond this)
    seed: int = 0
    # Thermal lag of the sensing element (s), or "auto" (searched), or None: the models see the logged
    # temperature. With a lag, the lag-corrected fit is used when it gains (thermal_lag_fit.py).
    thermal_lag_s: float | str | None = None
    # Hysteresis: fit per heating/cooling branch where that gains on held-out records (branch_fit.py).
    branch_fit: bool = False

    def __post_init__(self) -> None:
        if self.thermal_lag_s is not None and self.thermal_lag_s != "auto":
            from .thermal_lag_fit import MAX_TAU_S

            if isinstance(self.thermal_lag_s, bool) or not isinstance(self.thermal_lag_s, int | float) \
                    or not 0 < self.thermal_lag_s <= MAX_TAU_S:
                raise UserError(f"thermal lag must be 'auto' or a time constant in (0, {MAX_TAU_S:g}] s, "
                                f"not {self.thermal_lag_s!r}")
        if self.poly_method not in ("joint", "two_stage"):
            raise UserError(f"poly method must be 'joint' or 'two_stage', not {self.poly_method!r}")
        if not (self.poly_order == "cv" or (isinstance(self.poly_order, int) and self.poly_order >= 0)):
            raise UserError(f"polynomial order must be a non-negative integer or 'cv', not {self.poly_order!r}")
        for v in self.rbf_variants:
            if v not in VARIANTS:
                raise UserError(f"unknown RBF variant {v!r}; expected one of {', '.join(VARIANTS)}")
        if self.rbf_export and self.rbf_export not in self.rbf_variants:
            raise UserError(f"the exported RBF variant {self.rbf_export!r} is not among those trained "
                            f"({', '.join(self.rbf_variants) or 'none'})")
        for s in self.splits:
            if s not in SPLITS:
                raise UserError(f"unknown evaluation split {s!r}; expected one of {', '.join(SPLITS)}")


@dataclass
class Models:
    """Everything fitted from one set of records."""

    steps: TemperatureSteps
    six_position: dict[str, list[StepCalibration]]
    poly: dict[str, PolyModel]  # method -> model ("joint", "two_stage" when it can be fitted)
    poly_method: str
    rbf: dict[str, RbfModel]
    notes: list[str] = field(default_factory=list)

    @property
    def polynomial(self) -> PolyModel:
        return self.poly[self.poly_method]

    def compensators(self) -> dict[str, PolyModel | RbfModel]:
        """Models scored by the evaluation, by display name."""
        out: dict[str, PolyModel | RbfModel] = {"polynomial": self.polynomial}
        other = [m for m in self.poly if m != self.poly_method]
        for m in other:
            out[f"polynomial_{m}"] = self.poly[m]
        for v, model in self.rbf.items():
            out[f"rbf_{v}"] = model
        return out


def fit_models(records: Records, options: FitOptions, progress: Progress | None = None) -> Models:
    """Six-position per step, thermal polynomials and RBF networks from the given records."""
    if len(records) == 0:
        raise ValueError("no stable records to fit")
    ro = options.records
    steps = temperature_steps(records, ro.step_gap_c, ro.max_step_width_c, ro.continuous_gap_c, ro.ramp_bin_c)
    notes: list[str] = []
    if progress:
        progress(f"six-position calibration at {len(steps)} temperature step(s)")
    six = calibrate_steps(records, steps)
    polys: dict[str, dict[str, TriadPoly]] = {"joint": {}, "two_stage": {}}
    for triad in TRIADS:
        if options.poly_order == "cv":
            order, scores = cv_order(records, steps, triad, options.max_poly_order, options.poly_method,
                                     options.t_ref_c)
        else:
            order, scores = max_order(len(steps), int(options.poly_order)), {}
            if order < int(options.poly_order):
                notes.append(f"{triad}: {len(steps)} temperature step(s) support a polynomial of order {order} "
                             f"at most (asked for {options.poly_order})")
        if progress:
            progress(f"thermal polynomial ({triad}, order {order})")
        # Every power-on has its own gyro turn-on bias; fitted around, the runs' offsets do not bend the
        # thermal terms where the runs' temperatures differ. (Not the accelerometer's: with one
        # orientation per run it would confound bias and scale factor in every campaign.)
        offsets = triad == "gyro" and len(set(records.run.tolist())) > 1
        joint = fit_joint(records, triad, order, options.t_ref_c, run_offsets=offsets)
        if offsets:
            joint.notes.append(f"gyro: each of the {len(set(records.run.tolist()))} runs (power-ons) fitted with its "
                               "own offset (turn-on bias); the bias at t_ref is the runs' mean")
        joint.cv_scores = scores if options.poly_method == "joint" else {}
        polys["joint"][triad] = joint
        usable = [c for c in six[triad] if np.isfinite(c.params()).any()]
        if len(usable) >= order + 1:
            two = fit_two_stage(usable, order, options.t_ref_c, joint.t_min_c, joint.t_max_c)
            two.cv_scores = scores if options.poly_method == "two_stage" else {}
            polys["two_stage"][triad] = two
    poly = {m: PolyModel(accel=p["accel"], gyro=p["gyro"]) for m, p in polys.items() if len(p) == 2}
    if options.poly_method not in poly:
        raise ValueError(f"the {options.poly_method} polynomial cannot be fitted from these records")
    rbf = train_rbf_models(records, options.rbf_variants, base=poly[options.poly_method], options=options.rbf,
                           progress=progress) if options.rbf_variants else {}
    return Models(steps=steps, six_position=six, poly=poly, poly_method=options.poly_method, rbf=rbf, notes=notes)


@dataclass
class FitResult:
    """Models, evaluation and provenance of one `fit_campaign` call (see `to_dict`)."""

    options: FitOptions
    models: Models
    records: Records
    evaluation: list[SplitResult]
    provenance: dict[str, Any]
    data_summary: dict[str, Any]
    timings_s: dict[str, float]
    # The rows the figures of static samples draw (not serialised): the norms before and after
    # compensation and the Allan deviation need samples, not record means. A bounded set gathered at
    # the end of the fit (fit_rows.FigureRows), not the campaign's frame.
    samples: FigureRows | None = field(default=None, repr=False)
    # The measured gain of every model (evaluation name -> check): a model whose gain departs from the
    # fitted scale by more than gain.LIMIT is not exported.
    gains: dict[str, GainCheck] = field(default_factory=dict)
    # With FitOptions.thermal_lag_s: tau, its held-out gain over the plain fit and whether it is used.
    thermal_lag: LagReport | None = None
    # With FitOptions.branch_fit: the branch estimator, the widths, their held-out gain, whether used.
    branch: BranchReport | None = None

    @property
    def branch_model(self) -> BranchModel | None:
        """The branch the exported models take their outputs less (None: fitted without branches)."""
        return self.branch.model if self.branch else None

    @property
    def temperature_filter(self) -> TemperatureFilter | None:
        """The filter the exported models' temperature goes through (None: the logged temperature)."""
        return self.thermal_lag.temperature_filter if self.thermal_lag else None

    @property
    def polynomial(self) -> PolyModel:
        return self.models.polynomial

    @property
    def rbf_trained(self) -> RbfModel | None:
        """The network variant asked for export, whether or not its gain allows it."""
        return self.models.rbf.get(self.options.rbf_export) if self.options.rbf_export else None

    @property
    def rbf(self) -> RbfModel | None:
        """The exported network: the variant asked for, if its measured gain passes."""
        model = self.rbf_trained
        check = self.gains.get(f"rbf_{self.options.rbf_export}")
        return None if model is None or (check is not None and not check.passed) else model

    @property
    def not_exported(self) -> list[str]:
        """Why a model asked for is not in the model files (sentences)."""
        check = self.gains.get(f"rbf_{self.options.rbf_export}")
        if self.rbf_trained is None or check is None or check.passed:
            return []
        return [f"the RBF network {check.sentence()}; rbf.json and the C header hold the polynomial only"]

    @property
    def not_fitted(self) -> list[str]:
        """What the data cannot support, in sentences (empty when everything was fitted)."""
        out: list[str] = []
        for p in self.models.poly.get(self.models.poly_method, self.polynomial).triads().values():
            out.extend(p.not_fitted)
        for triad, cals in self.models.six_position.items():
            bad = [c for c in cals if c.not_fitted]
            if bad and not any(triad in s for s in out):
                temps = ", ".join(f"{c.temp_c:.1f}" for c in bad)
                out.append(f"{triad}: six-position calibration incomplete at {temps} C ({bad[0].not_fitted[0]})")
        for r in self.evaluation:
            if r.skipped:
                out.append(f"evaluation '{r.name}' skipped: {r.skipped}")
        return out

    @property
    def combined(self) -> list[str]:
        """Terms fitted only in combination, with the use the model is valid for (sentences)."""
        return [c for p in self.polynomial.triads().values() for c in p.combined]

    @property
    def unfinished(self) -> str | None:
        """A sentence when the data are of a campaign not recorded to its end, else None."""
        prov = self.provenance
        planned, recorded = prov.get("steps_planned"), prov.get("steps_recorded")
        if planned is None or recorded is None or recorded >= planned:
            return None
        return (f"unfinished campaign: {recorded} of {planned} planned steps recorded (status "
                f"{prov.get('status', '?')}); the models are fitted to what was recorded only")

    def export_provenance(self) -> dict[str, Any]:
        """What the model files carry about their origin: the data's provenance, how complete the
        campaign was, what was not fitted or only in combination, and why."""
        prov = dict(self.provenance)
        prov["unfinished"] = self.unfinished
        prov["not_fitted"] = self.not_fitted
        prov["combined"] = self.combined
        return json_clean(prov)

    @property
    def notes(self) -> list[str]:
        out = list(self.models.notes)
        if self.thermal_lag is not None:
            out.append(self.thermal_lag.sentence())
        if self.branch is not None:
            out.append(self.branch.sentence())
        for p in self.polynomial.triads().values():
            out.extend(p.notes)
        for m in self.models.rbf.values():
            out.extend(m.notes)
        return list(dict.fromkeys(out))

    def model_dicts(self) -> dict[str, Any]:
        """The exported models: {"polynomial": ..., "rbf": ...} (what `export` writes)."""
        out: dict[str, Any] = {"polynomial": self.polynomial.to_dict()}
        if self.rbf is not None:
            out["rbf"] = self.rbf.to_dict()
        if self.temperature_filter is not None:
            for d in out.values():
                d["temperature_filter"] = self.temperature_filter.to_dict()
        if self.branch_model is not None:
            for d in out.values():
                d["branch_state"] = self.branch_model.to_dict()
        return out

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (no NaN: unknown values are null): provenance, data summary, models,
        per-step calibration, evaluation."""
        return json_clean({
            "format": "labrunner-calibration/1",
            "provenance": self.export_provenance(),
            "data": self.data_summary,
            "options": _options_dict(self.options),
            "not_fitted": self.not_fitted,
            "notes": self.notes,
            "models": self.model_dicts(),
            "alternative_models": {
                **{f"polynomial_{m}": p.to_dict() for m, p in self.models.poly.items() if m != self.models.poly_method},
                **{f"rbf_{v}": {k: v2 for k, v2 in m.to_dict().items() if k != "base"}
                   for v, m in self.models.rbf.items() if v != self.options.rbf_export},
            },
            "six_position": {t: [c.to_dict() for c in cals] for t, cals in self.models.six_position.items()},
            "evaluation": [r.to_dict() for r in self.evaluation],
            "gains": {k: g.to_dict() for k, g in self.gains.items()},
            "not_exported": self.not_exported,
            "timings_s": self.timings_s,
            "thermal_lag": self.thermal_lag.to_dict() if self.thermal_lag else None,
            "branch": self.branch.to_dict() if self.branch else None,
        })


def json_clean(o: Any) -> Any:
    """Recursively: numpy scalars/arrays to Python, non-finite floats to None."""
    if isinstance(o, dict):
        return {str(k): json_clean(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [json_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return json_clean(o.tolist())
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not np.isfinite(o):
        return None
    return o


def _options_dict(o: FitOptions) -> dict[str, Any]:
    d = asdict(o)
    d["rbf_variants"] = list(o.rbf_variants)
    d["splits"] = list(o.splits)
    d["rbf"]["widths"] = list(o.rbf.widths)
    return d


def fit_campaign(frame: pd.DataFrame | CampaignRows, options: FitOptions | None = None,
                 provenance: dict[str, Any] | None = None, progress: Progress | None = None) -> FitResult:
    """Fit the calibration models to a campaign (a frame of campaign CSV columns, or its rows as chunks:
    `CampaignRows`) and evaluate them.

    The fit reads the rows chunk by chunk and keeps per-record summaries; the evaluation and the
    figures gather the rows they score or draw in further passes (docs/calibration.md, "Memory").
    `thermal_lag_s` and `branch_fit` filter the whole temperature series: with either, the campaign is
    read into one frame first.

    Raises `UserError` when the data holds nothing that can be fitted; otherwise fits
    what it can and lists the rest in `FitResult.not_fitted`.
    """
    opt = options or FitOptions()
    rows = frame if isinstance(frame, CampaignRows) else CampaignRows.of_frame(frame)
    with analysis_threads():
        if opt.branch_fit or opt.thermal_lag_s is not None:
            if rows.frame is None:
                log.info("thermal_lag_s / branch_fit filter the whole temperature series: the campaign is read "
                         "into one frame")
                if progress:
                    progress("reading the whole campaign (thermal_lag_s / branch_fit work on the whole series)")
            whole = rows.whole()
            if opt.branch_fit:
                return fit_with_branches(whole, opt, provenance, progress, _fit_inner)
            return _fit_inner(whole, opt, provenance, progress)
        return _fit_campaign(rows, opt, provenance, progress)


def _fit_inner(frame: pd.DataFrame, opt: FitOptions, provenance: dict[str, Any] | None,
               progress: Progress | None) -> FitResult:
    """The fit at the logged or, with a thermal lag, the lag-corrected temperature."""
    if opt.thermal_lag_s is not None:
        return fit_with_lag(frame, opt, provenance, progress, _fit_campaign)
    return _fit_campaign(frame, opt, provenance, progress)


def _fit(records: Records, opt: FitOptions, timings: dict[str, float], progress: Progress | None) -> Models:
    """The models of every record (`timings["fit"]`: how long that took)."""
    t1 = time.perf_counter()
    try:
        models = fit_models(records, opt, progress)
    except ValueError as exc:
        raise UserError(f"cannot fit: {exc}") from None
    timings["fit"] = time.perf_counter() - t1
    return models


class _FinalFitFailed(Exception):
    """The fit of every record failed while the evaluation ran: the evaluation stops at its next refit."""


def _fit_and_evaluate(rows: CampaignRows, n_rows: int, records: Records, opt: FitOptions,
                      timings: dict[str, float],
                      progress: Progress | None) -> tuple[Models, list[SplitResult], FigureRows]:
    """The models of every record, the evaluation and the figures' rows: the models, then the figures'
    rows, in a worker thread while the evaluation runs.

    They are independent (the evaluation refits its splits' training parts itself), so the worker uses
    the core the evaluation's passes over the rows leave idle. It fits a copy of `records` (its
    `temperature_steps` sets the copy's steps, the same as the original's), draws nothing at random and
    reads its own pass of the rows: the models and rows are those of a fit before the evaluation, bit for
    bit. Its memory comes and goes before the scoring: the evaluation's second pass waits for it."""
    steps = temperature_steps(records, opt.records.step_gap_c, opt.records.max_step_width_c,
                              opt.records.continuous_gap_c, opt.records.ramp_bin_c)
    if progress:
        progress("fitting the models alongside the evaluation")
    tuned_malloc()  # before the worker's first allocation: no arena of its own to keep what it frees
    with ThreadPoolExecutor(1, thread_name_prefix="labrunner-fit") as pool:
        final = pool.submit(_fit, copy.copy(records), opt, timings, None)
        figure_rows = pool.submit(gather_figure_rows, rows, records)  # after the fit (one worker)

        def refit(train: Records) -> dict[str, PolyModel | RbfModel]:
            if final.done() and final.exception() is not None:
                raise _FinalFitFailed  # a ValueError would read as this split's failure
            return fit_models(train, opt).compensators()

        passes = 0

        def chunks() -> Iterable[pd.DataFrame]:
            nonlocal passes
            passes += 1
            if passes > 1:
                figure_rows.exception()  # wait: the worker's memory is not held while the evaluation scores
            return rows.chunks()

        t2 = time.perf_counter()
        try:
            evaluation = evaluate_chunks(chunks, n_rows, records, steps, refit, opt.splits, opt.holdout_fraction,
                                         opt.eval_max_rows, opt.seed, progress, settle=figure_rows.exception)
        except BaseException:
            failed = final.exception()
            if failed is not None:  # the fit's own error, as when it came first
                raise failed from None
            raise
        timings["evaluation"] = time.perf_counter() - t2
        return final.result(), evaluation, figure_rows.result()


def _fit_campaign(data: pd.DataFrame | CampaignRows, opt: FitOptions, provenance: dict[str, Any] | None,
                  progress: Progress | None) -> FitResult:
    rows = data if isinstance(data, CampaignRows) else CampaignRows.of_frame(data)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if progress:
        progress("segmenting the rows into records" if rows.frame is None
                 else f"segmenting {len(rows.frame):,} rows into records")
    records, summary = read_records(rows, opt.records, progress)
    if len(records) == 0:
        raise UserError("no stable records in the data: every stretch is shorter than "
                        f"{opt.records.min_duration_s:g} s or drifts in temperature or rate")
    if rows.frame is not None:
        # The whole frame is at hand: the row-level fits (thermal lag, branches) look its rows up by record.
        records.row_record = records.labels(len(rows.frame))
    timings["records"] = time.perf_counter() - t0
    evaluation: list[SplitResult] = []
    if opt.evaluate:
        models, evaluation, samples = _fit_and_evaluate(rows, summary.rows, records, opt, timings, progress)
    else:
        models = _fit(records, opt, timings, progress)
        samples = gather_figure_rows(rows, records)
    if progress:
        progress("gain of every model over the training envelope")
    gains = check_models(dict(models.compensators()), models.polynomial, records, opt.seed)
    prov = dict(provenance or {})
    prov.setdefault("rows", summary.rows)
    prov["software"] = {"name": "labrunner", "version": __version__}
    prov["fitted_at"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    return FitResult(options=opt, models=models, records=records, evaluation=evaluation, provenance=prov,
                     data_summary=summary_dict(summary, records, models.steps), timings_s=timings,
                     samples=samples, gains=gains)
