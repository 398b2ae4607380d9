"""Which causes the data supports: forward selection on held-out, drift-whitened likelihood.

Criterion (per channel, smaller is better):

    score = M log(SSE_heldout / M) + log(M) * (identifiable coefficients)

SSE_heldout is -2 log p(held-out | training) under the drift model, summed over folds held
out by time blocks (crossval.py, drift.py), M the number of blocks: a held-out
log-likelihood with a BIC-sized parsimony charge. A term switched on for a channel costs at
least one parameter there (thermal_lag adds no coefficients but is still a choice), each
searched nonlinear parameter one more for the cause, and a cause is taken only if its total
improvement exceeds `min_evidence` (10, "strong" on the usual log-likelihood scale): it must
earn its parameters on data it was not fitted to, against a drift model that would
otherwise explain slow offsets.

Beyond the likelihood (`raw_check`), a cause must
- lower the held-out RMS of the raw rows, by at least `min_rms_gain` (0.1 %, an effect of
  about a twentieth of the per-row noise), on every channel it is named for: evidence
  against the drift model is not enough if the simulation would not predict better;
- show its own signature where it has one (per-run offsets must jump from run to run like
  independent turn-on offsets, not wander like a drift);
- exceed the data's resolution floor: a coarse temperature log, even de-quantised, leaves
  errors up to half a logger step times the channel's temperature slope that depend on how
  each soak was approached; smaller effects are not reported.

The search is greedy: add the best cause (each on the channels it explains best among all
candidates), repeat; then re-fit each selected cause with the others in place (its
nonlinear parameters and channels re-optimised, dropped if it no longer earns); then
re-estimate the drift with the causes in and go round again if it changed. Two causes are
confounded when the one not selected, put in place of the selected one, explains the
held-out data about as well (within `confound_margin`, allowing the ~1 per extra
coefficient that held-out likelihood charges), would also earn its keep, and needs at most
`confound_extra` more coefficients per channel to do it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from labrunner.domain import CHANNELS

from .engine import ChannelSystem, Engine
from .model import BASELINE, Selected, Spec, derivative_dot, lag_tau, replace, without
from .terms import Term

_GOLDEN = 0.5 * (np.sqrt(5.0) - 1.0)


@dataclass
class Evaluation:
    """A candidate term at given nonlinear parameters, on top of a specification."""

    term: str
    theta: dict[str, float]
    delta: dict[str, float] = field(default_factory=dict)  # penalised held-out improvement per channel
    fit_gain: dict[str, float] = field(default_factory=dict)  # unpenalised: M log(SSE_before / SSE_after)
    aliased: list[str] = field(default_factory=list)  # channels where the term adds nothing identifiable
    added: dict[str, int] = field(default_factory=dict)  # identifiable coefficients added per channel
    channels: list[str] = field(default_factory=list)
    score: float = -np.inf
    holdout: str = "short"  # the held-out stretches the score was judged on ("short" or "long")

    def selected(self) -> Selected:
        return Selected.make(self.term, self.theta, self.channels)


@dataclass
class Step:
    spec: Spec
    evaluations: list[Evaluation]


@dataclass
class Confound:
    selected: str
    alternative: Evaluation
    fit_selected: float
    fit_alternative: float


@dataclass
class SelectionResult:
    spec: Spec
    rho: dict[str, int]
    steps: list[Step]
    confounds: list[Confound]
    importance: dict[str, float]  # unpenalised held-out gain of each selected term given the others


class Searcher:
    def __init__(self, engine: Engine, terms: dict[str, Term], allowed: dict[str, set[str]],
                 min_evidence: float = 10.0, confound_margin: float = 10.0, refine_steps: int = 9,
                 min_rms_gain: float = 0.0, floors: dict[str, float] | None = None,
                 term_floors: dict[tuple[str, str], float] | None = None,
                 confound_extra: int = 4, long_engine: Engine | None = None) -> None:
        self.engine = engine
        # The same fits held out by hour-long stretches: a slow effect (per-run offsets, a slow
        # trend) is interpolated away by the drift level across a short stretch, not across an hour.
        self.long_engine = long_engine
        self.terms = terms
        self.allowed = allowed  # term -> channels on which the data can show it
        self.min_evidence = min_evidence
        self.confound_margin = confound_margin
        self.refine_steps = refine_steps
        self.min_rms_gain = min_rms_gain  # fraction by which the raw held-out RMS must drop
        self.floors = floors or {}  # channel -> peak-to-peak effect below which a term is an artifact
        self.term_floors = term_floors or {}  # (term, channel) -> the same, for one term
        self.confound_extra = confound_extra  # most extra coefficients per channel an alternative may use

    # -- one candidate -------------------------------------------------------------------

    def systems(self, spec: Spec, rho: dict[str, int], engine: Engine | None = None) -> dict[str, ChannelSystem]:
        eng = engine or self.engine
        return {c: eng.system(spec, c, rho[c]) for c in CHANNELS}

    def evaluate(self, spec: Spec, systems: dict[str, ChannelSystem], rho: dict[str, int], term: str,
                 theta: dict[str, float], slopes: dict[str, np.ndarray] | None = None,
                 only: list[str] | None = None, engine: Engine | None = None) -> Evaluation:
        """The term at fixed nonlinear parameters on top of `spec`, channel by channel.

        thermal_lag is evaluated exactly (the baseline refitted at the lagged temperature),
        or, given `slopes` (each channel's fitted d(error)/dT per row), linearised: one column
        slope * (T_element - T) -- cheap enough for the grid search.
        """
        t = self.terms[term]
        eng = engine or self.engine
        ev = Evaluation(term, dict(theta), holdout="short" if eng is self.engine else "long")
        pen = eng.penalty
        channels = [c for c in CHANNELS if c in self.allowed.get(term, set()) and (only is None or c in only)]
        cols = None if t.moves_baseline_temperature else eng.builder.columns(term, theta, lag_tau(spec))
        ctx = eng.builder.ctx
        lag = (ctx.element_temp(theta[t.lag_parameter]) - ctx.meas.temp_c) if slopes is not None else None
        for c in channels:
            base = systems[c].cv
            if t.moves_baseline_temperature and slopes is not None:
                cand = eng.try_columns(systems[c], ctx.blocks.mean(slopes[c] * lag)[:, None])
                added = 1
            elif t.moves_baseline_temperature:
                cand = eng.system(replace(spec, Selected.make(term, theta, {c})), c, rho[c]).cv
                added = 1
            else:
                assert cols is not None
                # Channels share columns (and often the drift rate), and the same candidate comes
                # back at every step: its whitened columns are cached.
                key = (term, tuple(sorted(theta.items())), lag_tau(spec) if t.uses_element_temperature else None,
                       c if t.per_channel_columns else "shared")
                cand = eng.try_columns(systems[c], eng.whiten_cached(key, rho[c], cols[c]))
                added = cand.n_params - base.n_params
                if added <= 0:
                    ev.aliased.append(c)
                    continue
            gain = base.n * float(np.log(max(base.sse, 1e-300) / max(cand.sse, 1e-300)))
            ev.fit_gain[c] = gain
            ev.added[c] = max(added, 1)
            ev.delta[c] = gain - pen * max(added, 1)
        ev.channels = [c for c in channels if ev.delta.get(c, -1.0) > 0]
        ev.score = (sum(ev.delta[c] for c in ev.channels) - pen * t.free_nonlinear) if ev.channels else -np.inf
        return ev

    def search_near(self, spec: Spec, systems: dict[str, ChannelSystem], rho: dict[str, int],
                    sel: Selected) -> Evaluation:
        """Re-optimise a selected term's nonlinear parameters near their current values (the
        polish: other terms have come in since it was found), exactly, and re-pick its channels."""
        t = self.terms[sel.term]
        # A lag is refitted exactly for each trial value: only on the channels it already has.
        only = sorted(sel.channels) if t.moves_baseline_temperature else None
        best = self.evaluate(spec, systems, rho, sel.term, sel.params, only=only)
        if not np.isfinite(_objective(best)):
            return best
        for p in t.nonlinear:
            if len(p.grid) < 2:
                continue
            v = best.theta[p.name]
            lo, hi = (v / 1.25, v * 1.25) if p.log else (v - 2.0, v + 2.0)
            best = self._golden(spec, systems, rho, sel.term, best, p.name, lo, hi, p.log, 5, None, only)
        return best

    def search(self, spec: Spec, systems: dict[str, ChannelSystem], rho: dict[str, int], term: str,
               refine_above: float | None = None) -> Evaluation:
        """Best nonlinear parameters on the grid, refined by golden-section steps.

        thermal_lag is searched linearised around the current fit (variable projection: the
        baseline coefficients fixed at their fit, one column per channel), then refined on
        the exact model near the linearised optimum, on the channels that could gain.
        Refinement is skipped when the best grid point's score is below `refine_above`
        (default: a few parameters' worth below zero): nothing near it can earn a place.
        """
        t = self.terms[term]
        slopes = self._lag_slopes(spec, systems) if t.moves_baseline_temperature else None
        evals = [self.evaluate(spec, systems, rho, term, th, slopes) for th in t.grid()]
        best = max(evals, key=_objective)
        floor = -3.0 * self.engine.penalty if refine_above is None else refine_above
        if not t.nonlinear or not np.isfinite(_objective(best)) or _objective(best) < floor:
            return best
        for p in t.nonlinear:
            values = np.asarray(p.grid, dtype=float)
            if values.size < 2:
                continue
            i = int(np.argmin(np.abs(values - best.theta[p.name])))
            lo, hi = values[max(i - 1, 0)], values[min(i + 1, values.size - 1)]
            best = self._golden(spec, systems, rho, term, best, p.name, lo, hi, p.log,
                                self.refine_steps if slopes is None else 5, slopes)
        if slopes is not None:
            hopeful = [c for c, d in best.delta.items() if d > -2 * self.engine.penalty]
            exact = self.evaluate(spec, systems, rho, term, best.theta, only=hopeful)
            if np.isfinite(_objective(exact)):
                tau = exact.theta[t.lag_parameter]
                exact = self._golden(spec, systems, rho, term, exact, t.lag_parameter, tau / 1.25, tau * 1.25, True,
                                     6, None, hopeful)
            best = exact
        return best

    def _lag_slopes(self, spec: Spec, systems: dict[str, ChannelSystem]) -> dict[str, np.ndarray]:
        """Each channel's fitted d(error)/dT per row, from its baseline coefficients."""
        meas = self.engine.builder.ctx.meas
        out = {}
        for i, c in enumerate(CHANNELS):
            beta, _ = self.engine.coefficients(spec, systems[c])
            coef = beta[systems[c].slices[BASELINE]]
            ref = meas.force_g if i < 3 else meas.rate_dps
            out[c] = derivative_dot(meas.temp_c, ref, coef)
        return out

    def _golden(self, spec: Spec, systems: dict[str, ChannelSystem], rho: dict[str, int], term: str,
                best: Evaluation, name: str, lo: float, hi: float, log: bool, steps: int,
                slopes: dict[str, np.ndarray] | None = None, only: list[str] | None = None) -> Evaluation:
        fwd = np.log if log else (lambda v: v)
        inv = np.exp if log else (lambda v: v)
        a, b = float(fwd(lo)), float(fwd(hi))

        seen: list[tuple[float, Evaluation]] = []

        def at(u: float) -> Evaluation:
            ev = self.evaluate(spec, systems, rho, term, {**best.theta, name: float(inv(u))}, slopes, only)
            seen.append((u, ev))
            return ev

        c, d = b - _GOLDEN * (b - a), a + _GOLDEN * (b - a)
        ec, ed = at(c), at(d)
        for _ in range(steps):
            if _objective(ec) >= _objective(ed):
                b, d, ed = d, c, ec
                c = b - _GOLDEN * (b - a)
                ec = at(c)
            else:
                a, c, ec = c, d, ed
                d = a + _GOLDEN * (b - a)
                ed = at(d)
        # Finish with parabolic steps through the best three points: a large effect needs its
        # time constant to a fraction of a percent, or what is left over looks like another cause.
        for _ in range(2):
            pts = sorted(seen, key=lambda p: -_objective(p[1]))[:3]
            if len(pts) < 3 or not all(np.isfinite(_objective(e)) for _, e in pts):
                break
            u = np.array([p[0] for p in pts])
            f = np.array([_objective(p[1]) for p in pts])
            den = (u[0] - u[1]) * (u[0] - u[2]) * (u[1] - u[2])
            if abs(den) < 1e-18:
                break
            aa = (u[2] * (f[1] - f[0]) + u[1] * (f[0] - f[2]) + u[0] * (f[2] - f[1])) / den
            bb = (u[2] ** 2 * (f[0] - f[1]) + u[1] ** 2 * (f[2] - f[0]) + u[0] ** 2 * (f[1] - f[2])) / den
            if aa >= 0:
                break
            vertex = -bb / (2 * aa)
            if not (u.min() <= vertex <= u.max()) or np.min(np.abs(u - vertex)) < 1e-9:
                break
            at(float(vertex))
        return max([best] + [e for _, e in seen], key=_objective)

    # -- the whole selection ------------------------------------------------------------------

    def run(self, rho: dict[str, int], max_terms: int = 5,
            drift_update: Callable[[Spec], dict[str, int]] | None = None) -> SelectionResult:
        """Select causes; `rho` is each channel's drift strength (index into the filter grid).

        `drift_update(spec)` re-estimates the drift once causes are in: a large effect the
        envelope model only approximates can inflate the first estimate, and a smaller
        effect only stands out against the right drift. At most three rounds; the causes are
always polished at the drift strength that is returned.
        """
        spec: Spec = ()
        steps: list[Step] = []
        candidates = [name for name in self.terms if self.allowed.get(name)]
        for round_ in range(3):
            while len(spec) < max_terms:
                systems = self.systems(spec, rho)
                evals = [self.search(spec, systems, rho, name) for name in candidates if name not in _names(spec)]
                evals = self._on_long_blocks(spec, rho, evals)
                steps.append(Step(spec, evals))
                best = None
                for ev in sorted(_own_channels(evals, self.engine.penalty, self.terms), key=_objective, reverse=True):
                    if ev.score <= self.min_evidence:
                        break
                    ev = self.raw_check(spec, rho, ev)
                    if ev.score > self.min_evidence:
                        best = ev
                        break
                if best is None:
                    break
                spec = replace(spec, best.selected())
            spec = self._polish(spec, rho)
            if drift_update is None or not spec or round_ == 2:
                break
            new = drift_update(spec)
            if new == rho:
                break
            rho = new
        confounds = self._confounds(spec, rho, candidates)
        importance = {s.term: self._gain_of(spec, rho, s) for s in spec}
        order = sorted(spec, key=lambda s: -importance[s.term])
        return SelectionResult(tuple(order), rho, steps, confounds, importance)

    def _on_long_blocks(self, spec: Spec, rho: dict[str, int], evals: list[Evaluation]) -> list[Evaluation]:
        """Each candidate at its best parameters judged again on hour-long held-out stretches; the
        better of the two judgements stands (both charge the same parameters)."""
        if self.long_engine is None:
            return evals
        systems = self.systems(spec, rho, self.long_engine)
        out = []
        for ev in evals:
            if not ev.delta:
                out.append(ev)
                continue
            long = self.evaluate(spec, systems, rho, ev.term, ev.theta, engine=self.long_engine)
            # Only channels where the short stretches' likelihood improves too: held out for an hour,
            # a cubic may extrapolate across a whole soak, and what repairs that is no cause.
            long.channels = [c for c in long.channels if ev.fit_gain.get(c, 0.0) > 0]
            long.score = (sum(long.delta[c] for c in long.channels) - self.engine.penalty
                          * self.terms[ev.term].free_nonlinear) if long.channels else -np.inf
            out.append(long if _objective(long) > _objective(ev) else ev)
        return out

    def _heldout(self, engine: Engine, spec: Spec, channel: str) -> float:
        """Held-out raw RMS of a specification on a channel (least squares, so independent of the drift)."""
        return engine.cached_heldout_rms(spec, channel)

    def raw_check(self, spec: Spec, rho: dict[str, int], ev: Evaluation) -> Evaluation:
        """Keep only the channels on which the term also lowers the held-out RMS of the raw rows.

        The whitened likelihood judges against the drift model; this judges the prediction a
        simulation would make. A term that fits the fine structure of something else -- the
        rounding of a coarse temperature log, say -- can win the first and lose the second.
        """
        kept = []
        term = self.terms[ev.term]
        for c in ev.channels:
            before = self._heldout(self.engine, spec, c)
            after_spec = replace(spec, Selected.make(ev.term, ev.theta, {c}))
            system = self.engine.system(after_spec, c, rho[c])
            after = self._heldout(self.engine, after_spec, c)
            floor = max(self.floors.get(c, 0.0), self.term_floors.get((ev.term, c), 0.0))
            if floor > 0 and ev.term in system.slices:
                beta, _ = self.engine.coefficients(after_spec, system)
                sl = system.slices[ev.term]
                effect = self.engine.builder.design(after_spec, c).x[:, sl] @ beta[sl]
                if np.ptp(effect) <= floor:
                    continue
            if term.consistent_fn is not None:
                part = self.engine.term_fit(after_spec, system, ev.term)
                if not term.consistent(part.coef, part.schur):
                    continue
            better = after < before * (1.0 - self.min_rms_gain)
            if better and self.long_engine is not None:
                # And no worse on hour-long held-out stretches (within the same 0.1 %).
                long_before = self._heldout(self.long_engine, spec, c)
                long_after = self._heldout(self.long_engine, after_spec, c)
                if long_after > long_before * (1.0 + self.min_rms_gain):
                    continue
            if better:
                kept.append(c)
        if kept == ev.channels:
            return ev
        out = Evaluation(ev.term, dict(ev.theta), dict(ev.delta), dict(ev.fit_gain), list(ev.aliased), dict(ev.added))
        out.channels = kept
        out.score = (sum(ev.delta[c] for c in kept) - self.engine.penalty * self.terms[ev.term].free_nonlinear
                     if kept else -np.inf)
        return out

    def _polish(self, spec: Spec, rho: dict[str, int]) -> Spec:
        """Re-search each selected term with the others in place; drop what no longer earns."""
        for _ in range(2):
            changed = False
            for sel in list(spec):
                if sel.term not in _names(spec):
                    continue
                rest = without(spec, sel.term)
                ev = self.search_near(rest, self.systems(rest, rho), rho, sel)
                ev = self._on_long_blocks(rest, rho, [ev])[0]
                if ev.score > self.min_evidence:
                    ev = self.raw_check(rest, rho, ev)
                if ev.score <= self.min_evidence:
                    spec = rest
                    changed = True
                elif ev.selected() != sel:
                    spec = _substitute(spec, ev.selected())
                    changed = True
            if not changed:
                break
        return spec

    def _gain_of(self, spec: Spec, rho: dict[str, int], sel: Selected) -> float:
        ev = self.own_evaluation(spec, rho, sel)
        return float(sum(ev.fit_gain.get(c, 0.0) for c in sel.channels))

    def own_evaluation(self, spec: Spec, rho: dict[str, int], sel: Selected) -> Evaluation:
        """A selected term's evaluation given the others, on the held-out stretches it was judged on."""
        rest = without(spec, sel.term)
        ev = self.evaluate(rest, self.systems(rest, rho), rho, sel.term, sel.params)
        return self._on_long_blocks(rest, rho, [ev])[0]

    def _confounds(self, spec: Spec, rho: dict[str, int], candidates: list[str]) -> list[Confound]:
        out: list[Confound] = []
        for sel in spec:
            rest = without(spec, sel.term)
            systems = self.systems(rest, rho)
            # Like for like: both causes' fit on the short held-out stretches (a per-run term cannot
            # predict a power-on held out whole, so on long stretches it would never look confounded).
            own = self.evaluate(rest, systems, rho, sel.term, sel.params)
            fit_a = sum(own.fit_gain.get(c, 0.0) for c in sel.channels)
            for name in candidates:
                if name in _names(spec):
                    continue
                # Only an alternative that could come near the selected cause is worth refining.
                short = self.search(rest, systems, rho, name, refine_above=0.5 * fit_a - self.confound_margin)
                ev = self._on_long_blocks(rest, rho, [short])[0]
                if ev.score <= self.min_evidence:
                    continue
                ev = self.raw_check(rest, rho, ev)
                if ev.score <= self.min_evidence:
                    continue
                ev.fit_gain, ev.added = short.fit_gain, short.added
                fit_b = sum(max(ev.fit_gain.get(c, 0.0), 0.0) for c in sel.channels)
                # Held-out likelihood charges about 1 per coefficient a fit does not need, so an
                # alternative that fits as well with more coefficients shows that much less. But
                # one that needs many more coefficients to mimic the selected cause is told apart
                # by the data's own consistency (e.g. 36 per-run offsets lining up into 3
                # g-sensitivities): only a few extra per channel count as confounding.
                extra = [ev.added.get(c, 0) - own.added.get(c, 0) for c in sel.channels]
                if max(extra, default=0) > self.confound_extra:
                    continue
                if fit_b + max(sum(extra), 0) >= fit_a - self.confound_margin:
                    out.append(Confound(sel.term, ev, fit_a, fit_b))
        return out


def _own_channels(evals: list[Evaluation], penalty: float, terms: dict[str, Term]) -> list[Evaluation]:
    """Each candidate restricted to the channels it explains best among all candidates.

    Greedy selection by total score would let a broad cause (per-run offsets, say) take a
    channel that another cause explains better with fewer parameters (a branch offset that
    happens to be constant within each run), and that cause would then find nothing left.
    """
    best: dict[str, float] = {}
    for ev in evals:
        for c in ev.channels:
            best[c] = max(best.get(c, -np.inf), ev.delta[c])
    out = []
    for ev in evals:
        mine = [c for c in ev.channels if ev.delta[c] >= best[c]]
        if mine == ev.channels:
            out.append(ev)
            continue
        r = Evaluation(ev.term, dict(ev.theta), dict(ev.delta), dict(ev.fit_gain), list(ev.aliased), dict(ev.added))
        r.channels = mine
        r.score = sum(ev.delta[c] for c in mine) - penalty * terms[ev.term].free_nonlinear if mine else -np.inf
        out.append(r)
    return out


def _objective(ev: Evaluation) -> float:
    """Search objective: the cause's score; without any channel, the best channel's delta (for the search to climb)."""
    if ev.channels:
        return ev.score
    return max(ev.delta.values(), default=-1e300) - 1e12


def _names(spec: Spec) -> list[str]:
    return [s.term for s in spec]


def _substitute(spec: Spec, sel: Selected) -> Spec:
    return tuple(sel if s.term == sel.term else s for s in spec)
