"""The effect registry: every IMU effect's forward error equals its regressors x coefficients.

One class per effect owns the simulator's formula and the diagnosis's regressors; these
tests check, effect by effect at random parameters and random inputs, that the two are
the same model, that each effect's parameters survive JSON, and that an effect taken out
of the registry is gone from the simulator, the diagnosis and the docs' cause table.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import numpy as np
import pytest

from labrunner.domain import CHANNELS, ORIENTATIONS, UP_VECTORS
from labrunner.imu import effects
from labrunner.imu.baseline import baseline_design
from labrunner.imu.cause_table import cause_table, table_in, with_table
from labrunner.imu.effect import Effect
from labrunner.imu.effects import REGISTRY
from labrunner.imu.inputs import ImuInputs
from labrunner.imu.model import EFFECT_TYPES, ImuModel, ModelState, default_imu_model
from labrunner.imu.samples import SampleContext

ROOT = Path(__file__).resolve().parents[2]
NAMES = sorted(REGISTRY)
N = 600


def _seed(*parts: str) -> int:
    return zlib.crc32("/".join(parts).encode()) % 100_000


def random_inputs(rng: np.random.Generator, n: int = N) -> ImuInputs:
    """Irregular times, four power-ons, a temperature wandering up and down over the range, and
    arbitrary specific force and rotation (not only about a body axis)."""
    dt = rng.uniform(0.5, 30.0, n)
    t = 1000.0 + np.cumsum(dt)
    run = 1 + np.searchsorted(np.sort(rng.choice(np.arange(50, n - 50), 3, replace=False)), np.arange(n), "right")
    first = np.array([t[run == r][0] for r in run])
    temp = np.clip(20.0 + np.cumsum(rng.normal(0.0, 0.8, n)), -25.0, 55.0)
    up = UP_VECTORS[rng.integers(0, len(ORIENTATIONS), n)]
    force = up + rng.normal(0.0, 0.2, (n, 3))
    rate = rng.normal(0.0, 80.0, (n, 3))
    return ImuInputs(t_s=t, run=run, t_on_s=t - first, temp_c=temp, force_g=force, rate_dps=rate)


def _rng_for(name: str) -> int:
    return _seed("stochastic", name)


def forward_alone(model: ImuModel, name: str, inputs: ImuInputs, stochastic_seed: int) -> np.ndarray:
    """(N, 6) what the effect adds to the model's error (the same generator state as the regressors)."""
    with_effect, _ = model.deterministic_error(inputs, rng=np.random.default_rng(stochastic_seed))
    without, _ = model.with_effects(**{name: None}).deterministic_error(inputs)
    return with_effect - without


def regressors_times_coefficients(eff: Effect, ctx: SampleContext, seed: int,
                                  element_tau: float | None = None) -> np.ndarray:
    rows = type(eff).regressors(ctx, eff.theta(), element_tau)
    coef = eff.coefficients(ctx, seed)
    out = np.tile(eff.intercept(ctx, seed), (len(ctx.rows), 1))
    for c, x in rows.items():
        out[:, CHANNELS.index(c)] += x @ coef[c]
    return out


@pytest.mark.parametrize("trial", range(3))
@pytest.mark.parametrize("name", NAMES)
def test_forward_error_equals_regressors_times_coefficients(name: str, trial: int) -> None:
    rng = np.random.default_rng(_seed(name, str(trial)))
    cls = REGISTRY[name]
    eff = cls.random(rng)
    inputs = random_inputs(rng)
    model = default_imu_model(seed=int(rng.integers(0, 1000))).with_effects(**{name: eff})
    ctx = SampleContext(inputs, rng=np.random.default_rng(_rng_for(name)))
    forward = forward_alone(model, name, inputs, _rng_for(name))

    if cls.moves_baseline_temperature:
        # The baseline's own regressors at the element temperature, times the baseline's coefficients.
        element = ctx.element_temp(eff.theta()[cls.lag_parameter])
        total, _ = model.deterministic_error(inputs)
        expected = np.empty_like(total)
        for i, c in enumerate(CHANNELS):
            triad, ref = (model.accel, inputs.force_g) if i < 3 else (model.gyro, inputs.rate_dps)
            temp = element if c in eff.channels else inputs.temp_c  # type: ignore[attr-defined]
            expected[:, i] = baseline_design(temp, ref) @ triad.coefficients()[i % 3]
        assert np.max(np.abs(total - expected)) < 1e-9
        assert np.any(np.abs(forward) > 1e-6)  # the lag does something on these inputs
        return

    expected = regressors_times_coefficients(eff, ctx, model.seed)
    assert np.any(np.abs(forward) > 1e-9), "the random parameters switch nothing on"
    assert np.max(np.abs(forward - expected)) < 1e-9


@pytest.mark.parametrize("name", [n for n in NAMES if not REGISTRY[n].moves_baseline_temperature])
def test_block_regressors_and_predictions_agree_with_the_row_regressors(name: str) -> None:
    cls = REGISTRY[name]
    rng = np.random.default_rng(_seed("blocks", name))
    eff = cls.random(rng)
    inputs = random_inputs(rng)
    seed = 11
    rows = cls.regressors(SampleContext(inputs, rng=np.random.default_rng(1)), eff.theta(), None)
    blocks = cls.block_regressors(SampleContext(inputs, rng=np.random.default_rng(1)), eff.theta(), None)
    coef = eff.coefficients(SampleContext(inputs), seed)
    for c, x in rows.items():
        assert x.shape[0] == N and c in cls.acts_on
        if blocks is not None:  # each sample its own block: the block means are the rows
            assert np.array_equal(blocks[c], x)
        predicted = cls.predict(SampleContext(inputs, rng=np.random.default_rng(1)), eff.theta(), None, c, coef[c])
        assert np.allclose(predicted, x @ coef[c], rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", [n for n in NAMES if REGISTRY[n].uses_element_temperature])
def test_an_effect_of_the_element_temperature_follows_the_lag(name: str) -> None:
    movers = [n for n in NAMES if REGISTRY[n].moves_baseline_temperature]
    if not movers:
        pytest.skip("no effect moves the baseline's temperature")
    rng = np.random.default_rng(_seed("element", name))
    lag = REGISTRY[movers[0]].random(rng)
    eff = REGISTRY[name].random(rng)
    inputs = random_inputs(rng)
    model = default_imu_model().with_effects(**{movers[0]: lag})
    extended = model.with_effects(**{name: eff})
    forward = extended.deterministic_error(inputs)[0] - model.deterministic_error(inputs)[0]
    tau = lag.theta()[REGISTRY[movers[0]].lag_parameter]
    expected = regressors_times_coefficients(eff, SampleContext(inputs), 0, element_tau=tau)
    assert np.max(np.abs(forward - expected)) < 1e-9


@pytest.mark.parametrize("name", NAMES)
def test_streaming_in_chunks_with_carried_state_equals_one_batch(name: str) -> None:
    rng = np.random.default_rng(_seed("chunks", name))
    eff = REGISTRY[name].random(rng)
    inputs = random_inputs(rng)
    model = default_imu_model(seed=5).with_effects(**{name: eff})
    whole, _ = model.deterministic_error(inputs, rng=np.random.default_rng(9))
    gen = np.random.default_rng(9)
    parts, state = [], ModelState()
    for lo, hi in ((0, 250), (250, 251), (251, N)):
        chunk = ImuInputs(**{k: np.asarray(v)[lo:hi] for k, v in vars(inputs).items()})
        err, state = model.deterministic_error(chunk, state, gen)
        parts.append(err)
    assert np.allclose(np.concatenate(parts), whole, rtol=0, atol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_parameters_round_trip_through_json(name: str) -> None:
    cls = REGISTRY[name]
    eff = cls.random(np.random.default_rng(_seed("json", name)))
    text = json.dumps(eff.to_dict())
    back = cls.from_dict(json.loads(text))
    assert back == eff
    assert back.to_dict() == eff.to_dict()
    model = default_imu_model(seed=2).with_effects(**{name: eff})
    again = ImuModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert again.effects[name] == eff
    inputs = random_inputs(np.random.default_rng(3))
    assert np.array_equal(again.deterministic_error(inputs)[0], model.deterministic_error(inputs)[0])


@pytest.mark.parametrize("name", NAMES)
def test_parameters_are_validated_by_the_effect(name: str) -> None:
    with pytest.raises(ValueError, match=name):
        REGISTRY[name].from_dict({"no_such_parameter": 1.0})


def test_every_pair_of_confounders_has_one_sentence_owned_by_one_of_the_two() -> None:
    seen: dict[frozenset[str], str] = {}
    for name, cls in REGISTRY.items():
        for other, sentence in cls.separates.items():
            assert other in REGISTRY and other != name, (name, other)
            key = frozenset({name, other})
            assert key not in seen, f"{sorted(key)} told apart twice: by {seen[key]} and {name}"
            seen[key] = name
            assert sentence and sentence[-1] != "."


def test_the_registry_is_every_effect_module_in_registry_order() -> None:
    modules = sorted(p.stem for p in (ROOT / "labrunner/imu/effects").glob("*.py") if not p.stem.startswith("_"))
    assert sorted(REGISTRY) == modules
    orders = [cls.order for cls in REGISTRY.values()]
    assert orders == sorted(orders)
    assert list(EFFECT_TYPES) == list(REGISTRY)


def test_the_docs_cause_table_is_generated_from_the_registry() -> None:
    doc = (ROOT / "docs/diagnosis.md").read_text()
    assert table_in(doc) == cause_table(), "run `python -m labrunner.imu.effects --write docs/diagnosis.md`"
    for name, cls in REGISTRY.items():
        assert f"| `{name}`" in cause_table() and cls.json_parameters in cause_table()
    assert with_table(doc) == doc


# --- taking an effect out ------------------------------------------------------------------


def _measurements(rng: np.random.Generator):
    from labrunner.discrepancy.blocks import make_blocks
    from labrunner.discrepancy.measurements import Measurements

    inputs = random_inputs(rng, 400)
    orient = np.repeat(np.arange(4), 100)
    force = UP_VECTORS[orient]
    rate = force * np.where(np.arange(400) % 50 < 25, 50.0, -50.0)[:, None]
    meas = Measurements(
        t_s=inputs.t_s, run=inputs.run, orientation=orient, temp_c=inputs.temp_c, chamber_c=inputs.temp_c,
        table_rate_dps=rate.sum(axis=1), force_g=force, rate_dps=rate, t_on_s=inputs.t_on_s,
        output=np.concatenate([force, rate], axis=1), row_dt_s=1.0, temperature_quantum_c=None)
    return meas, make_blocks(meas)


@pytest.mark.parametrize("name", NAMES)
def test_an_effect_taken_out_of_the_registry_is_gone_everywhere(monkeypatch, name: str) -> None:
    from labrunner.discrepancy.coverage import assess
    from labrunner.discrepancy.terms import TermContext, candidate_terms

    meas, blocks = _measurements(np.random.default_rng(1))
    assert (name in candidate_terms(TermContext(meas, blocks))) == REGISTRY[name].candidate
    assert f"| `{name}`" in cause_table()
    eff = REGISTRY[name].random(np.random.default_rng(2))

    monkeypatch.delitem(effects.REGISTRY, name)

    assert name not in EFFECT_TYPES
    with pytest.raises(ValueError, match=f"unknown effect '{name}'"):
        default_imu_model().with_effects(**{name: eff.to_dict()})
    with pytest.raises(ValueError, match=f"unknown effect '{name}'"):
        ImuModel.from_dict({"effects": {name: {}}})
    terms = candidate_terms(TermContext(meas, blocks))
    assert name not in terms and terms, "the other candidates remain"
    assert name not in assess(meas).excluded
    assert f"`{name}`" not in cause_table()


def _in_a_copy(tmp_path: Path, edit, script: str) -> None:
    """Run `script` in a fresh interpreter against a copy of the package changed by `edit(copy)`."""
    copy = tmp_path / "labrunner"
    shutil.copytree(ROOT / "labrunner", copy, ignore=shutil.ignore_patterns("__pycache__"))
    edit(copy)
    script = "import os, labrunner\nassert labrunner.__file__.startswith(os.environ['EFFECTS_COPY'])\n" + script
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "EFFECTS_COPY": str(tmp_path)}
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120,
                         cwd=tmp_path)  # not the repository: its labrunner/ would come first on sys.path
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_deleting_an_effect_file_removes_it_with_no_other_edit(tmp_path: Path) -> None:
    """The real thing: a copy of the package without warmup.py."""
    _in_a_copy(tmp_path, lambda copy: (copy / "imu/effects/warmup.py").unlink(), textwrap.dedent("""
        from labrunner.imu.model import EFFECT_TYPES, default_imu_model
        from labrunner.imu.cause_table import cause_table
        from labrunner.discrepancy.terms import cause_order
        assert "warmup" not in EFFECT_TYPES and "hysteresis" in EFFECT_TYPES
        assert "warmup" not in cause_order() and "thermal_lag" in cause_order()
        assert "`warmup`" not in cause_table() and "`hysteresis`" in cause_table()
        try:
            default_imu_model().with_effects(warmup={"tau_s": 100.0})
        except ValueError as exc:
            assert "unknown effect 'warmup'" in str(exc)
        else:
            raise AssertionError("warmup still known")
        print("ok")
    """))


NEW_EFFECT = '''
from dataclasses import dataclass, field
import numpy as np
from labrunner.domain import CHANNELS
from ..effect import Effect, channel_map, channel_vector, per_channel, same_for, scalars


@dataclass
class RateOffset(Effect):
    name = "rate_offset"
    order = 85
    what = "an offset proportional to the table rate's magnitude"
    driver = "the table rate"
    json_parameters = "`k`: {channel: offset per deg/s}"
    k: dict = field(default_factory=dict)

    def validate(self):
        self.k = channel_map(self.k)

    def forward(self, stream):
        speed = np.linalg.norm(np.asarray(stream.inputs.rate_dps, float), axis=1)
        return speed[:, None] * channel_vector(self.k)[None, :], None

    @classmethod
    def regressors(cls, ctx, theta, element_tau):
        return same_for(CHANNELS, np.linalg.norm(np.asarray(ctx.rows.rate_dps, float), axis=1))

    def coefficients(self, ctx, seed):
        return per_channel(self.k)

    @classmethod
    def summarize(cls, fit, ctx):
        return {"k": scalars(fit)}, {"k": scalars(fit)}
'''


def test_adding_a_cause_is_one_file(tmp_path: Path) -> None:
    _in_a_copy(tmp_path, lambda copy: (copy / "imu/effects/rate_offset.py").write_text(NEW_EFFECT), textwrap.dedent("""
        import numpy as np
        from labrunner.imu.model import EFFECT_TYPES, ImuInputs, default_imu_model
        from labrunner.imu.cause_table import cause_table
        from labrunner.discrepancy.terms import cause_order
        assert list(EFFECT_TYPES)[-3:] == ["rate_offset", "bias_random_walk", "bias_instability"]
        assert "rate_offset" in cause_order() and "| `rate_offset` |" in cause_table()
        n = 5
        inputs = ImuInputs(t_s=np.arange(n, dtype=float), run=np.ones(n, int), t_on_s=np.arange(n, dtype=float),
                           temp_c=np.full(n, 25.0), force_g=np.tile([0, 0, 1.0], (n, 1)),
                           rate_dps=np.tile([0, 0, 40.0], (n, 1)))
        base = default_imu_model()
        extra = base.with_effects(rate_offset={"k": {"gyro_z": 1e-3}}).deterministic_error(inputs)[0]
        assert np.allclose(extra - base.deterministic_error(inputs)[0], [[0, 0, 0, 0, 0, 0.04]] * n)
        print("ok")
    """))
