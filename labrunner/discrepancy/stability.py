"""How stable a verdict is: each finding's evidence re-judged on resampled time stretches.

A cause that clears the evidence threshold on the whole log may fall below it on most parts of
it (an evidence of 12 against 10 is a coin toss). So the log's hour-long stretches are resampled
(`SUBSAMPLES` draws, each keeping 80 % of them, seeded: the same data gives the same answer) and
each selected cause -- and the best cause not selected -- is judged again on each draw: its
held-out score restricted to the kept blocks (`Engine.block_contributions`: the score splits
exactly by block, so nothing is refitted), the same parameter charge, the same threshold. A
finding selected on fewer than `LEVEL` of the draws is marked uncertain, and so is the verdict.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from labrunner.domain import CHANNELS

from .engine import Engine
from .model import Selected, Spec, replace, without
from .selection import Searcher

log = logging.getLogger(__name__)

SUBSAMPLES = 10
KEEP = 0.8
LEVEL = 0.8  # selected on at least this share of the draws: stable; below: uncertain


@dataclass
class Stability:
    selected_share: float  # of the draws on which the cause clears the evidence threshold
    subsamples: int
    whole_score: float = float("nan")  # the same score on the whole log (all blocks)

    @property
    def uncertain(self) -> bool:
        return self.selected_share < LEVEL

    def to_json(self) -> dict[str, float | int | bool]:
        return {"selected_share": round(self.selected_share, 2), "subsamples": self.subsamples,
                "uncertain": self.uncertain, "level": LEVEL}


def resamples(stretch: np.ndarray, seed: int = 11) -> list[np.ndarray]:
    """SUBSAMPLES boolean masks over blocks, each keeping a random 80 % of the stretches."""
    ids = np.unique(stretch)
    rng = np.random.default_rng(seed)
    keep = max(1, int(round(KEEP * ids.size)))
    return [np.isin(stretch, rng.choice(ids, size=keep, replace=False)) for _ in range(SUBSAMPLES)]


def stability(searcher: Searcher, base: Spec, rho: dict[str, int], sel: Selected, holdout: str,
              masks: list[np.ndarray]) -> Stability:
    """Share of the draws on which `sel`, added to `base`, clears the evidence threshold (its channels
    re-picked on each draw: those whose share of the score improves by more than the charge)."""
    engine: Engine = searcher.long_engine if holdout == "long" and searcher.long_engine else searcher.engine
    term = searcher.terms[sel.term]
    pen = engine.penalty
    before, after, added = {}, {}, {}
    for c in CHANNELS:
        if c not in sel.channels:
            continue
        s0 = engine.system(base, c, rho[c])
        s1 = engine.system(replace(base, Selected(sel.term, sel.theta, frozenset({c}))), c, rho[c])
        before[c], after[c] = engine.block_contributions(s0), engine.block_contributions(s1)
        added[c] = max(s1.cv.n_params - s0.cv.n_params, 1)
    passed = 0
    whole = np.ones(next(iter(before.values())).size, dtype=bool) if before else None
    for mask in ([whole] if whole is not None else []) + masks:
        n = int(mask.sum())
        score = -pen * term.free_nonlinear
        for c in before:
            b, a = float(before[c][mask].sum()), float(after[c][mask].sum())
            delta = n * float(np.log(max(b, 1e-300) / max(a, 1e-300))) - pen * added[c]
            score += max(delta, 0.0)
        if mask is whole:
            full = score  # the whole log's score by the same arithmetic
            continue
        passed += score > searcher.min_evidence
    return Stability(passed / len(masks), len(masks), full if before else -np.inf)


def finding_stability(searcher: Searcher, spec: Spec, rho: dict[str, int], sel: Selected, holdout: str,
                      masks: list[np.ndarray]) -> Stability:
    """A selected cause, judged with the other selected causes in place."""
    return stability(searcher, without(spec, sel.term), rho, sel, holdout, masks)
