"""The engine's memory is bounded in bytes, not in entries (issue 15, target 3): a campaign of longer records
has more blocks, and each cached whitened part grows with them. What is evicted is whitened again, to
the same numbers, so a diagnosis is the same whatever the caches hold."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from labrunner.discrepancy import diagnose
from labrunner.discrepancy.engine import ChannelFit, ChannelSystem, _ByteLru
from labrunner.discrepancy.selection import Searcher
from tests.discrepancy.campaigns import campaign, draw_thermal_lag

engine_module = importlib.import_module("labrunner.discrepancy.engine")
diagnose_module = importlib.import_module("labrunner.discrepancy.diagnose")


def test_the_byte_cache_drops_the_least_recently_used_first_and_keeps_the_newest() -> None:
    cache: _ByteLru[np.ndarray] = _ByteLru(100, lambda a: int(a.nbytes))
    a, b, c = (np.zeros(5) for _ in range(3))  # 40 bytes each
    cache.put("a", a)
    cache.put("b", b)
    assert cache.get("a") is a  # now the most recent: b goes first
    cache.put("c", c)
    assert (cache.get("b"), cache.get("a"), cache.get("c"), cache.bytes) == (None, a, c, 80)
    big = np.zeros(50)  # 400 bytes: over the budget alone, kept (it is in use), the rest dropped
    assert cache.put("big", big) is big
    assert (len(cache), cache.bytes, cache.get("big") is big) == (1, 400, True)


@pytest.fixture(scope="module")
def frame():
    hidden = draw_thermal_lag(np.random.default_rng(7))
    return campaign([hidden], "sims", 7)[0]


def _caches(captured: list) -> list[_ByteLru]:
    return [cache for diagnoser in captured for engine in (diagnoser.engine, diagnoser.long_engine)
            for cache in (engine._xcache, engine._zcache)]


def test_a_diagnosis_is_the_same_whatever_its_caches_can_hold(frame, monkeypatch: pytest.MonkeyPatch) -> None:
    captured: list = []
    init = diagnose_module._Diagnoser.__init__

    def keep(self, *args, **kwargs):
        init(self, *args, **kwargs)
        captured.append(self)

    monkeypatch.setattr(diagnose_module._Diagnoser, "__init__", keep)
    roomy = diagnose(frame).to_json()
    assert any(len(cache) > 1 for cache in _caches(captured))  # the caches were used
    assert all(cache.bytes <= cache.max_bytes for cache in _caches(captured))
    captured.clear()
    monkeypatch.setattr(engine_module, "_DESIGN_CACHE_BYTES", 1)
    monkeypatch.setattr(engine_module, "_COLUMN_CACHE_BYTES", 1)
    tight = diagnose(frame).to_json()
    assert all(len(cache) <= 1 for cache in _caches(captured))  # every part whitened again when asked for
    roomy.pop("seconds"), tight.pop("seconds")
    assert tight == roomy
    assert roomy["verdict"] == "thermal_lag"


def test_a_prediction_fit_holds_the_grams_only_and_fits_as_the_whole_system(frame,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    found: list = []
    run = Searcher.run

    def keep(self, *args, **kwargs):
        result = run(self, *args, **kwargs)
        found.append((self.engine, result.spec))
        return result

    monkeypatch.setattr(Searcher, "run", keep)
    diagnose(frame)
    eng, selected = found[0]
    assert selected  # the thermal lag: a spec beyond the baseline
    for spec in ((), selected):
        for c in ("accel_x", "gyro_z"):
            fit, whole = eng.prediction_system(spec, c), eng.system(spec, c, 0)
            assert type(fit) is ChannelFit and isinstance(whole, ChannelSystem)
            assert not hasattr(fit, "x")
            np.testing.assert_array_equal(eng.coefficients(spec, fit)[0], eng.coefficients(spec, whole)[0])
            np.testing.assert_array_equal(eng.residual(spec, fit), eng.residual(spec, whole))
            assert eng.heldout_rms(spec, fit) == eng.heldout_rms(spec, whole)
