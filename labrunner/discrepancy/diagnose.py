"""`diagnose`: fit the simulator's IMU model to measured data, find what it gets wrong, extend it.

Pipeline: validate rows -> assess what the campaign can identify -> cut blocks ->
estimate each channel's drift under the envelope model -> forward-select causes on
held-out, drift-whitened likelihood -> fit the selected model -> extended sims model,
held-out gains, confounded alternatives -> a `Diagnosis` (JSON, report).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from labrunner.blas_threads import analysis_threads
from labrunner.domain import CHANNELS
from labrunner.errors import UserError
from labrunner.imu.effects import drift_effect
from labrunner.imu.model import ImuModel

from .advice import separating_measurement
from .allan import TARGET as ALLAN_TARGET
from .allan import AllanCurve, NoiseFit, fit_noise, interval_json
from .blocks import make_blocks
from .coverage import Coverage, assess
from .crossval import elapsed_s, long_folds, long_segment_length, segment_length, time_folds
from .drift import build_drift_filter
from .engine import Engine
from .envelope import envelope_columns
from .extend import ChannelNoise, build_model, check_model, noise_density, row_spacing, white_rms, with_noise
from .measurements import Measurements
from .model import BASELINE, DesignBuilder, Selected, Spec, channel_list, derivative_dot, replace, without
from .residuals import residual_table
from .selection import Evaluation, Searcher, SelectionResult
from .stability import LEVEL, Stability, finding_stability, resamples, stability
from .summary import sample_rms
from .terms import TermContext, TermFit, candidate_terms

_MIN_BLOCKS = 40
_MIN_FOLDS = 2  # held-out stretches with data: each fold's fit needs training data outside it
_DRIFT_EVIDENCE = 10.0


class TooLittleData(UserError):
    """The rows cannot support a held-out diagnosis; the message says how much there is and what is needed
    (the command prefixes the data's name)."""


def _logged_s(meas: Measurements) -> float:
    """Seconds of data: the time each run spans, summed."""
    frame = pd.DataFrame({"run": meas.run, "t": meas.t_s})
    spans = frame.groupby("run")["t"].agg(lambda t: t.max() - t.min())
    return float(spans.sum())


@dataclass
class DiagnoseOptions:
    n_folds: int = 5
    min_evidence: float = 10.0  # penalised held-out 2*delta-log-likelihood a cause must exceed
    confound_margin: float = 10.0  # an alternative within this much of the selected cause is confounded
    min_rms_gain: float = 0.001  # and it must lower a channel's held-out raw RMS by this fraction (0.1 %)
    max_causes: int = 5
    block_s: float | None = None  # None: chosen from the data size
    causes: tuple[str, ...] | None = None  # restrict the candidates (default: all)
    # The rate table's accuracy (relative): the logged reference rate may be off by this much per
    # record, so a gyro term growing with the rate must exceed it (the paper's table: +-0.01 %).
    rate_accuracy: float = 1e-4


@dataclass
class Gain:
    heldout_rms_before: dict[str, float]
    heldout_rms_after: dict[str, float]

    @property
    def improvement_by_channel(self) -> dict[str, float]:
        return {c: 100.0 * (1.0 - self.heldout_rms_after[c] / b) if b > 0 else 0.0
                for c, b in self.heldout_rms_before.items()}

    @property
    def improvement_pct(self) -> float:
        """Mean over the channels of the per-channel held-out RMS reduction, in percent."""
        values = list(self.improvement_by_channel.values())
        return float(np.mean(values)) if values else 0.0

    def to_json(self) -> dict[str, Any]:
        return {"heldout_rms_before": _round(self.heldout_rms_before),
                "heldout_rms_after": _round(self.heldout_rms_after),
                "improvement_pct": round(self.improvement_pct, 2),
                "improvement_pct_by_channel": {c: round(v, 2) for c, v in self.improvement_by_channel.items()}}


@dataclass
class Finding:
    cause: str
    channels: list[str]
    parameters: dict[str, Any]
    gain: Gain
    evidence_score: float  # penalised held-out evidence (2 delta log-likelihood), > min_evidence to be selected
    status: str  # "selected" or "alternative" (explains the data as well as a selected, confounded cause)
    confounded_with: list[str] = field(default_factory=list)
    evidence: str = ""
    effect: dict[str, Any] = field(default_factory=dict)  # the sims effect reproducing it
    stability: Stability | None = None  # how often it is selected on resampled time stretches

    def to_json(self) -> dict[str, Any]:
        return {"cause": self.cause, "channels": self.channels, "parameters": _round(self.parameters),
                "gain": self.gain.to_json(), "confounded_with": self.confounded_with, "evidence": self.evidence,
                "status": self.status, "evidence_score": _finite(self.evidence_score),
                "stability": self.stability.to_json() if self.stability else None}


@dataclass
class Diagnosis:
    verdict: str
    findings: list[Finding]
    not_identifiable: list[str]
    gain: Gain  # baseline against the extended model, every channel (short held-out stretches)
    gain_long: Gain  # the same on hour-long held-out stretches
    noise: dict[str, ChannelNoise]
    coverage: Coverage
    candidates: list[dict[str, Any]]
    model: ImuModel
    model_check: dict[str, dict[str, float]]  # RMS of measured minus model, baseline and extended
    residuals: pd.DataFrame
    method: dict[str, Any]
    seconds: float
    model_path: str | None = None
    verdict_note: str = ""  # why the verdict is uncertain ("" when it is stable)
    allan: NoiseFit | None = None  # Allan deviation of the residuals and the noise model fitted to it
    runner_up: dict[str, Any] | None = None  # the best cause not selected and how often it would be

    @property
    def verdict_uncertain(self) -> bool:
        return bool(self.verdict_note)

    @property
    def selected(self) -> list[Finding]:
        return [f for f in self.findings if f.status == "selected"]

    def to_json(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict,
            "verdict_uncertain": self.verdict_uncertain,
            "verdict_note": self.verdict_note,
            "runner_up": self.runner_up,
            "findings": [f.to_json() for f in self.findings],
            "not_identifiable": self.not_identifiable,
            "gain": self.gain.to_json(),
            "gain_long_blocks": self.gain_long.to_json(),
            "extended_model": {
                "path": self.model_path,
                "effects": sorted(self.model.effects),
                "residual_rms": {k: _round(v) for k, v in self.model_check.items()},
            },
            "noise": {c: {"white_rms": _sig(n.white_rms), "noise_density": _sig(n.noise_density),
                          "drift_per_sqrt_s": _sig(n.drift_per_sqrt_s), "drift_evidence": round(n.drift_evidence, 1)}
                      for c, n in self.noise.items()},
            "allan": _allan_json(self.allan),
            "coverage": self.coverage.to_json(),
            "candidates": self.candidates,
            "method": self.method,
            "seconds": round(self.seconds, 2),
        }


def diagnose(data: pd.DataFrame | Measurements, options: DiagnoseOptions | None = None) -> Diagnosis:
    """Diagnose measured campaign rows (campaign-CSV columns, or prepared `Measurements`)."""
    options = options or DiagnoseOptions()
    started = time.perf_counter()
    meas = data if isinstance(data, Measurements) else Measurements.from_frame(data)
    with analysis_threads():
        return _Diagnoser(meas, options).run(started)


class _Diagnoser:
    def __init__(self, meas: Measurements, options: DiagnoseOptions) -> None:
        self.meas = meas
        self.options = options
        self.coverage = assess(meas)
        elapsed = elapsed_s(meas.t_s)
        self.long_segment_s = long_segment_length(float(elapsed[-1]) if elapsed.size else 0.0, options.n_folds)
        self.blocks = make_blocks(meas, options.block_s, cut_every_s=self.long_segment_s, elapsed_s=elapsed)
        if len(self.blocks) < _MIN_BLOCKS:
            raise TooLittleData(f"too little data to diagnose: {len(meas)} rows over {_logged_s(meas):.0f} s make "
                                f"{len(self.blocks)} blocks of steady conditions; the diagnosis needs at least "
                                f"{_MIN_BLOCKS}")
        self.ctx = TermContext(meas, self.blocks)
        self.terms = candidate_terms(self.ctx)
        wanted = set(options.causes) if options.causes else set(self.terms)
        unknown = wanted - set(self.terms)
        if unknown:
            raise UserError(f"unknown cause(s) {', '.join(sorted(unknown))}; expected some of {', '.join(self.terms)}")
        self.allowed = {name: set(t.channels) - self.coverage.excluded.get(name, set())
                        for name, t in self.terms.items() if name in wanted}
        self.builder = DesignBuilder(self.ctx, self.terms)
        err = meas.error
        self.segment_s = segment_length(self.blocks, options.n_folds)
        folds = time_folds(self.blocks, options.n_folds, self.segment_s)
        if np.unique(folds).size < _MIN_FOLDS:
            raise TooLittleData(
                f"too little data to diagnose: {len(meas)} rows over {_logged_s(meas):.0f} s; the diagnosis holds "
                f"out {self.segment_s:.0f} s stretches of each run in turn and needs data in at least {_MIN_FOLDS} "
                f"of them: more than {self.segment_s:.0f} s in a run, or several runs (a campaign as `labrunner "
                "export` writes it)")
        drift = build_drift_filter(self.blocks)
        self.engine = Engine(self.builder, self.blocks, self.blocks.mean(err), drift, folds, options.n_folds)
        self.long_engine = Engine(self.builder, self.blocks, self.engine.y, drift,
                                  long_folds(self.blocks, elapsed, options.n_folds, self.long_segment_s),
                                  options.n_folds)
        self.searcher = Searcher(self.engine, self.terms, self.allowed, options.min_evidence, options.confound_margin,
                                 min_rms_gain=options.min_rms_gain, floors=self._floors(),
                                 term_floors=self._rate_floors(options.rate_accuracy),
                                 # hour-long stretches judge causes only in a record of ten hours or more
                                 long_engine=self.long_engine if self.long_segment_s >= 3600.0 else None)

    def _drift(self, spec: Spec, envelope: dict[str, np.ndarray]) -> dict[str, int]:
        """Drift strength per channel with the selected causes switched on for every channel they
        could affect (a cause found on one channel may be hiding, as drift, on another). Per-run
        offsets do not enter: the drift filter restarts at every power-on."""
        wide = tuple(Selected(s.term, s.theta, frozenset(self.allowed.get(s.term, s.channels))) for s in spec)
        return {c: self.engine.estimate_rho(wide, c, envelope[c]) for c in CHANNELS}

    def _rate_floors(self, accuracy: float) -> dict[tuple[str, str], float]:
        """A gyro's squared-rate term smaller than the table's rate accuracy at the highest rate
        cannot be told from the reference's own error (a per-record scale error)."""
        top = float(np.max(np.abs(self.meas.table_rate_dps))) if len(self.meas) else 0.0
        floors = {(name, c): t.effect.rate_floor(c, top, accuracy) for name, t in self.terms.items() for c in CHANNELS}
        return {k: v for k, v in floors.items() if v > 0}

    def _floors(self) -> dict[str, float]:
        """Per channel, the peak-to-peak effect a coarse temperature log can fake: half a logger
        step times the channel's (fitted, RMS) temperature slope. De-quantised, the log is off
        by a fraction of a step that depends on how each soak was approached and on how fast
        the temperature rose after a power-on -- fake branch offsets, transients, offsets."""
        q = self.meas.temperature_quantum_c
        if not q:
            return {}
        floors = {}
        n = self.blocks.weight.astype(float)
        w = np.sqrt(n)[:, None]
        for i, c in enumerate(CHANNELS):
            x = self.builder.baseline(c, None)
            coef = np.linalg.lstsq(x * w, self.engine.y[:, i] * w[:, 0], rcond=None)[0]
            ref = self.meas.force_g if i < 3 else self.meas.rate_dps
            slope = derivative_dot(self.meas.temp_c, ref, coef)
            floors[c] = 0.5 * q * float(np.sqrt(np.mean(slope * slope)))
        return floors

    def run(self, started: float) -> Diagnosis:
        eng = self.engine
        envelope = envelope_columns(self.builder, eng.y)
        rho_select = {c: eng.estimate_rho((), c, envelope[c]) for c in CHANNELS}
        result = self.searcher.run(rho_select, self.options.max_causes, lambda s: self._drift(s, envelope))
        spec = result.spec
        rho = result.rho  # the drift strength the causes were judged at
        # The model is fitted by least squares (the drift judged the causes, it does not take
        # what temperature explains); `gain` and the held-out RMS use the same fit.
        systems = {c: eng.prediction_system(spec, c) for c in CHANNELS}
        base_systems = {c: eng.prediction_system((), c) for c in CHANNELS}

        findings = self._findings(result, spec, rho, systems)
        noise = self._noise(spec)
        coefficients = {c: eng.coefficients(spec, systems[c])[0][systems[c].slices[BASELINE]] for c in CHANNELS}
        effects = {f.cause: f.effect for f in findings if f.status == "selected"}
        walk = {c: n.drift_per_sqrt_s for c, n in noise.items() if n.drift_evidence > _DRIFT_EVIDENCE}
        drift = drift_effect()
        if walk and drift is not None:  # the drift of the noise model, as the simulator's effect
            effects[drift.name] = drift.from_drift(walk)
        model = build_model(coefficients, effects, noise)
        noise_fit = self._noise_fit(model, noise)
        if noise_fit is not None and noise_fit.finding is not None:
            model = noise_fit.model  # the fitted noise model replaces the drift-only one
        base_coef = {c: eng.coefficients((), base_systems[c])[0] for c in CHANNELS}
        baseline_model = build_model(base_coef, {}, noise)

        gain = Gain({c: eng.heldout_rms((), base_systems[c]) for c in CHANNELS},
                    {c: eng.heldout_rms(spec, systems[c]) for c in CHANNELS})
        long = self.long_engine
        gain_long = Gain({c: long.heldout_rms((), long.prediction_system((), c)) for c in CHANNELS},
                         {c: long.heldout_rms(spec, long.prediction_system(spec, c)) for c in CHANNELS})
        residuals = residual_table(self.meas, self.blocks,
                                   np.column_stack([eng.residual((), base_systems[c]) for c in CHANNELS]),
                                   np.column_stack([eng.residual(spec, systems[c]) for c in CHANNELS]))
        notes = list(self.ctx.resolution_notes)
        notes += [n for name, t in self.terms.items() if self.allowed.get(name) for n in t.notes(self.ctx)]
        not_identifiable = list(self.coverage.not_identifiable) + notes + self._aliased(result)
        verdict = findings[0].cause if findings and findings[0].status == "selected" else "none"
        runner_up = self._stability(result, spec, rho, findings)
        note = _verdict_note(verdict, findings, runner_up)
        if noise_fit is not None and noise_fit.finding is not None:
            findings.append(noise_fit.finding)  # among the findings, never the verdict
        return Diagnosis(
            verdict_note=note, runner_up=runner_up, allan=noise_fit.fit if noise_fit else None,
            verdict=verdict, findings=findings, not_identifiable=not_identifiable, gain=gain, gain_long=gain_long,
            noise=noise,
            coverage=self.coverage, candidates=self._candidates(result), model=model,
            model_check={"baseline": self._check_model(baseline_model), "extended": self._check_model(model)},
            residuals=residuals, method=self._method(), seconds=time.perf_counter() - started)

    # -- findings ------------------------------------------------------------------------

    def _fit_term(self, spec: Spec, sel: Selected, rho: dict[str, int]) -> tuple[dict[str, Any], dict[str, Any]]:
        term = self.terms[sel.term]
        fit = TermFit(theta=sel.params, coef={}, cov={}, schur={})
        for c in channel_list(sel.channels):
            system = self.engine.prediction_system(spec, c)
            if term.moves_baseline_temperature:
                fit.coef[c] = np.zeros(0)
                continue
            part = self.engine.term_fit(spec, system, sel.term)
            fit.coef[c], fit.cov[c], fit.schur[c] = part.coef, part.cov, part.schur
        return term.summarize(fit, self.ctx)

    def _gain(self, before: Spec, after: Spec, channels: list[str], rho: dict[str, int]) -> Gain:
        eng = self.engine
        return Gain({c: eng.heldout_rms(before, eng.system(before, c, rho[c])) for c in channels},
                    {c: eng.heldout_rms(after, eng.system(after, c, rho[c])) for c in channels})

    def _findings(self, result: SelectionResult, spec: Spec, rho: dict[str, int], systems: dict) -> list[Finding]:
        findings: list[Finding] = []
        confounds = {s.term: [c for c in result.confounds if c.selected == s.term] for s in spec}
        for sel in spec:
            params, effect = self._fit_term(spec, sel, rho)
            channels = channel_list(sel.channels)
            rest = without(spec, sel.term)
            own = self.searcher.own_evaluation(spec, rho, sel)
            term = self.terms[sel.term]
            alts = confounds[sel.term]
            stretches = "hour-long" if own.holdout == "long" else f"{self.segment_s:.0f} s"
            evidence = (f"{term.what}. Held-out evidence {own.score:.0f} (drift-whitened 2*delta-log-likelihood on "
                        f"{stretches} time blocks held out, after a log(M) charge per parameter; > "
                        f"{self.options.min_evidence:g} counts) on "
                        + ", ".join(f"{c} {own.delta.get(c, 0.0):.0f}" for c in channels) + ".")
            for alt in alts:
                evidence += (f" The data cannot tell it from {alt.alternative.term}, which explains "
                             f"{alt.fit_alternative:.0f} against {alt.fit_selected:.0f}: "
                             + separating_measurement(term, self.terms[alt.alternative.term]) + ".")
            finding = Finding(sel.term, channels, params, self._gain(rest, spec, channels, rho), own.score, "selected",
                              [a.alternative.term for a in alts], evidence, effect)
            findings.append(finding)
            for alt in alts:
                findings.append(self._alternative(spec, sel, alt.alternative, rho, alt.fit_selected,
                                                  alt.fit_alternative))
        return findings

    def _alternative(self, spec: Spec, sel: Selected, ev: Evaluation, rho: dict[str, int], fit_a: float,
                     fit_b: float) -> Finding:
        rest = without(spec, sel.term)
        alt_spec = replace(rest, ev.selected())
        params, effect = self._fit_term(alt_spec, ev.selected(), rho)
        channels = list(ev.channels)
        evidence = (f"{self.terms[ev.term].what}. Explains the held-out data about as well as {sel.term} "
                    f"({fit_b:.0f} against {fit_a:.0f}) but with more parameters or less support, so {sel.term} is "
                    f"preferred; to separate them: " + separating_measurement(self.terms[sel.term], self.terms[ev.term])
                    + ".")
        return Finding(ev.term, channels, params, self._gain(rest, alt_spec, channels, rho), ev.score, "alternative",
                       [sel.term], evidence, effect)

    # -- stability -------------------------------------------------------------------------------

    def _stability(self, result: SelectionResult, spec: Spec, rho: dict[str, int],
                   findings: list[Finding]) -> dict[str, Any] | None:
        """Each selected finding's share of resampled time stretches on which it is selected; and
        the best cause not selected, with its share (a verdict `none` can be marginal too)."""
        stretch = np.floor(elapsed_s(self.meas.t_s)[self.blocks.start] / self.long_segment_s).astype(np.int64)
        masks = resamples(stretch)
        by_term = {s.term: s for s in spec}
        for f in findings:
            if f.status == "selected" and f.cause in by_term:
                own = self.searcher.own_evaluation(spec, rho, by_term[f.cause])
                f.stability = finding_stability(self.searcher, spec, rho, by_term[f.cause], own.holdout, masks)
        # Only a cause turned down for want of evidence can be a near miss; one whose evidence cleared
        # the threshold but failed the checks beyond it (raw held-out RMS, its signature) is not.
        last = [ev for ev in (result.steps[-1].evaluations if result.steps else [])
                if ev.term not in by_term and ev.delta and ev.score <= self.options.min_evidence]
        if not last:
            return None
        best = max(last, key=lambda ev: max(ev.delta.values()))
        channels = list(best.channels) or [max(best.delta, key=best.delta.__getitem__)]
        share = stability(self.searcher, spec, rho, Selected.make(best.term, best.theta, channels), best.holdout,
                          masks)
        if share.whole_score > self.options.min_evidence:
            # Judged this way it would pass on the whole log too: it was turned down by the selection's
            # own channel and drift rules, not on evidence, and is no near miss of the resamples.
            return None
        return {"cause": best.term, "channels": channel_list(set(channels)), "evidence_score": _finite(best.score),
                "stability": {"selected_share": round(share.selected_share, 2), "subsamples": share.subsamples}}

    # -- the noise ------------------------------------------------------------------------------

    def _noise_fit(self, model: ImuModel, noise: dict[str, ChannelNoise]) -> _NoiseResult | None:
        """Allan deviation of the residual under the extended model, the noise model fitted to it;
        a `noise` finding when the simulator's noise as it stood (white only) misses the measured
        Allan deviation by more than the target at some octave."""
        predicted, _ = model.deterministic_error(self.meas.imu_inputs())
        white = np.array([noise[c].noise_density for c in CHANNELS])
        fit = fit_noise(self.meas, self.meas.error - predicted, np.nan_to_num(white))
        if fit is None:
            return None
        off = [c for c in CHANNELS if fit.mismatch_before[c] > ALLAN_TARGET]
        if not off:
            return _NoiseResult(fit, None, model)
        extended = with_noise(model, np.array([fit.white[c] for c in CHANNELS]),
                              np.array([fit.bias_instability[c] for c in CHANNELS]),
                              np.array([fit.rate_random_walk[c] for c in CHANNELS]))
        gain = AllanGain(dict(fit.mismatch_before), dict(fit.mismatch_after))
        taus = fit.measured.tau_s
        evidence = (f"the simulator's noise model (white noise only) departs from the Allan deviation of the "
                    f"residuals by up to {max(fit.mismatch_before.values()):.0%} over the octaves of tau from "
                    f"{taus[0]:g} s to {taus[-1]:g} s; with the fitted white noise, bias instability and rate "
                    f"random walk by up to {max(fit.mismatch_after.values()):.0%} (target {ALLAN_TARGET:.0%}; the "
                    "top octaves rest on few independent differences, so the measured curve itself scatters there)")
        parameters = {"white": fit.white, "bias_instability": fit.bias_instability,
                      "rate_random_walk": fit.rate_random_walk}
        finding = Finding("noise", off, parameters, gain, float("nan"), "noise", [], evidence,
                          {k: v for k, v in extended.effects.items() if k in ("bias_instability", "bias_random_walk")})
        return _NoiseResult(fit, finding, extended)

    # -- the rest of the report ------------------------------------------------------------------

    def _noise(self, spec: Spec) -> dict[str, ChannelNoise]:
        """White noise and drift of each channel under the extended model."""
        summary = self.meas.summary
        if summary is not None and summary.raw_density is not None:
            # Summaries of raw samples: the white noise is the samples' (measured before averaging),
            # its RMS over the samples as if they were the rows.
            density = summary.raw_density
            raw = np.where(summary.averaged, summary.raw_spacing_s or self.meas.row_dt_s, row_spacing(self.meas))
            n = summary.samples.astype(float)
            spacing = np.array([n.sum() / float(n @ (1.0 / raw))])  # white_rms's mean of 1/(2 dt) over samples
        else:
            density = noise_density(self.meas, self.blocks)
            spacing = row_spacing(self.meas)
        out = {}
        for i, c in enumerate(CHANNELS):
            rho = self.engine.estimate_rho(spec, c)
            _, s2 = self.engine.coefficients(spec, self.engine.system(spec, c, rho))
            evidence = self.engine.drift_evidence(spec, c, rho) if rho > 0 else 0.0
            out[c] = ChannelNoise(white_rms=white_rms(float(density[i]), spacing),
                                  noise_density=float(density[i]),
                                  drift_per_sqrt_s=self.engine.drift.drift_per_sqrt_s(rho, s2),
                                  drift_evidence=float(evidence))
        return out

    def _check_model(self, model: ImuModel) -> dict[str, float]:
        """`extend.check_model`, over the raw samples when the rows summarise them."""
        if self.meas.summary is None:
            return check_model(model, self.meas)
        predicted, _ = model.deterministic_error(self.meas.imu_inputs())
        rms = sample_rms(self.meas.summary, self.meas.error - predicted)
        return {c: float(rms[i]) for i, c in enumerate(CHANNELS)}

    def _aliased(self, result: SelectionResult) -> list[str]:
        """Causes the numerical check found indistinguishable from the baseline on some channels."""
        seen: dict[str, set[str]] = {}
        for step in result.steps[:1]:
            for ev in step.evaluations:
                if ev.aliased:
                    seen.setdefault(ev.term, set()).update(ev.aliased)
        return [f"{t} on {', '.join(channel_list(chs))}: indistinguishable from the baseline model in this data"
                for t, chs in seen.items()]

    def _candidates(self, result: SelectionResult) -> list[dict[str, Any]]:
        first = {ev.term: ev for ev in result.steps[0].evaluations} if result.steps else {}
        last = {ev.term: ev for ev in result.steps[-1].evaluations} if result.steps else {}
        selected = {s.term for s in result.spec}
        out = []
        for name in self.terms:
            entry: dict[str, Any] = {"cause": name, "tested_on": channel_list(self.allowed.get(name, set())),
                                     "selected": name in selected}
            if name in first:
                entry["evidence_vs_baseline"] = _finite(first[name].score)
                entry["best_parameters_vs_baseline"] = _round(first[name].theta)
            if name in last and name not in selected:
                entry["evidence_given_selected"] = _finite(last[name].score)
            out.append(entry)
        return out

    def _method(self) -> dict[str, Any]:
        return {
            "criterion": "held-out (time-block cross-validated) -2 log-likelihood of drift-whitened residuals "
                         "+ log(M) per identifiable coefficient; a cause must improve it by more than min_evidence",
            "folds": self.options.n_folds, "holdout_segment_s": round(self.segment_s, 1),
            "holdout_long_segment_s": round(self.long_segment_s, 1),
            "fit": "deterministic terms by weighted least squares on block means (the drift model weighs the "
                   "evidence only)",
            "blocks": len(self.blocks), "block_s": round(self.blocks.block_s, 2),
            "penalty_per_parameter": round(self.engine.penalty, 3), "min_evidence": self.options.min_evidence,
            "confound_margin": self.options.confound_margin,
        }


@dataclass
class _NoiseResult:
    fit: NoiseFit
    finding: Finding | None
    model: ImuModel  # the extended model with the fitted noise model (when there is a finding)


class AllanGain(Gain):
    """The noise finding's gain: the simulated against the measured Allan deviation, as the largest
    relative departure over the octaves, before and after (held-out RMS says nothing of noise)."""

    def to_json(self) -> dict[str, Any]:
        return {"allan_mismatch_before": _round(self.heldout_rms_before),
                "allan_mismatch_after": _round(self.heldout_rms_after),
                "improvement_pct": round(self.improvement_pct, 2),
                "improvement_pct_by_channel": {c: round(v, 2) for c, v in self.improvement_by_channel.items()}}


def _allan_json(fit: NoiseFit | None) -> dict[str, Any] | None:
    if fit is None:
        return None
    def curve(c: AllanCurve) -> dict[str, list[float]]:
        return {ch: [_sig(float(v), 4) for v in c.adev[:, i]] for i, ch in enumerate(CHANNELS)}
    return {"tau_s": [float(t) for t in fit.measured.tau_s], "measured": curve(fit.measured),
            "simulated_before": curve(fit.before), "simulated_after": curve(fit.after),
            "mismatch_before": _round(fit.mismatch_before), "mismatch_after": _round(fit.mismatch_after),
            "target": ALLAN_TARGET, "measured_interval_68": interval_json(fit.measured),
            "excess_before": _round(fit.excess_before), "excess_after": _round(fit.excess_after),
            "parameters": {"white": _round(fit.white), "bias_instability": _round(fit.bias_instability),
                           "rate_random_walk": _round(fit.rate_random_walk)}}


def _verdict_note(verdict: str, findings: list[Finding], runner_up: dict[str, Any] | None) -> str:
    """Why the verdict is uncertain, or "" when every selected finding and the verdict are stable."""
    parts = []
    for f in findings:
        if f.status == "selected" and f.stability is not None and f.stability.uncertain:
            parts.append(f"{f.cause} is selected on only {f.stability.selected_share:.0%} of "
                         f"{f.stability.subsamples} resampled time stretches (stable from {LEVEL:.0%})")
    if runner_up and runner_up["stability"]["selected_share"] >= 1.0 - LEVEL:
        parts.append(f"{runner_up['cause']}, not selected, would be on {runner_up['stability']['selected_share']:.0%} "
                     "of them")
    if not parts:
        return ""
    return f"verdict {verdict} is uncertain: " + "; ".join(parts)


def _sig(v: float, digits: int = 6) -> float:
    if v is None or not np.isfinite(v):
        return None  # type: ignore[return-value]
    return float(f"{v:.{digits}g}")


def _round(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _round(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_round(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return _sig(float(value))
    if isinstance(value, np.integer):
        return int(value)
    return value


def _finite(v: float) -> float | None:
    return round(float(v), 1) if np.isfinite(v) else None
