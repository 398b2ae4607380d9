"""The paper's INS test (Sec. V.C): navigation errors after 60 s windows fall with compensation."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from labrunner.calibration.fit import FitOptions, fit_campaign
from labrunner.calibration.ins import navigate
from labrunner.calibration.report import summary_markdown
from labrunner.cli import main


def test_navigation_of_a_known_bias_matches_the_closed_form() -> None:
    """A constant accelerometer bias b along x, no rotation: x error b g t^2 / 2 after t."""
    n, b = 600, 1e-3
    ref = np.tile([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (n, 1))
    val = ref + [b, 0, 0, 0, 0, 0]
    dist, ang = navigate(val, ref, np.arange(n)[None], window_s=60.0)
    assert abs(dist[0] - b * 9.80665 * 60 ** 2 / 2) < 1e-6 * dist[0] and ang[0] < 1e-9
    # a gyro bias about x tilts gravity into y: attitude error = bias x t
    val = ref + [0, 0, 0, 0.01, 0, 0]
    dist, ang = navigate(val, ref, np.arange(n)[None], window_s=60.0)
    assert abs(ang[0] - 0.6) < 1e-9 and dist[0] > 0


def test_fit_reports_the_ins_test_on_static_held_out_rows(cubic_campaign) -> None:
    result = fit_campaign(cubic_campaign, FitOptions(splits=("random", "between_temperatures")))
    rnd, between = result.evaluation
    assert rnd.ins_skipped and not rnd.ins  # scattered rows make no window
    ins = between.ins
    assert ins["raw"].n_windows > 10 and ins["raw"].window_s == 60.0
    exported = f"rbf_{result.rbf.variant}" if result.rbf is not None else "polynomial"
    for name in ("polynomial", exported):
        assert ins[name].position_m < 0.2 * ins["raw"].position_m, (name, ins[name], ins["raw"])
        assert ins[name].attitude_deg < 0.2 * ins["raw"].attitude_deg
    assert "INS test (the paper's Sec. V.C)" in summary_markdown(result)
    assert result.to_dict()["evaluation"][1]["ins"]["raw"]["n_windows"] == ins["raw"].n_windows


def test_compensate_ins_option_on_a_csv(cubic_campaign, tmp_path: Path, capsys) -> None:
    csv = tmp_path / "c.csv"
    cubic_campaign.to_csv(csv, index=False)
    assert main(["fit", str(csv), "--no-eval", "--quiet", "--out", str(tmp_path / "fit")]) == 0
    capsys.readouterr()
    assert main(["compensate", str(tmp_path / "fit" / "polynomial.json"), str(csv), "--csv",
                 str(tmp_path / "o.csv"), "--ins"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("INS test")]
    raw = next(line for line in lines if "INS test, raw:" in line)
    comp = next(line for line in lines if "INS test, polynomial:" in line)

    def pos(line: str) -> float:
        return float(line.split("position error ")[1].split(" m")[0])

    assert pos(comp) < 0.2 * pos(raw)
    assert main(["compensate", str(tmp_path / "fit" / "polynomial.json"), str(csv), "--csv",
                 str(tmp_path / "o2.csv"), "--ins", "-5"]) == 2
    assert "--ins must be a positive number" in capsys.readouterr().err


def _static_sequence(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times, records and static flags of a campaign's rows: 50 Hz records (one at 100 Hz) at store-like
    times, dropped samples, rotating rows inside records, a repeated time, gaps and back-to-back records."""
    t, lab, static = [], [], []
    t0 = 1e5
    for r in range(24):
        rate = 100.0 if r % 7 == 3 else 50.0
        tt = t0 + np.arange(int(rng.integers(500, 9000))) / rate
        tt = tt[rng.random(tt.size) > 0.001]
        st = np.ones(tt.size, dtype=bool)
        if r % 5 == 1:
            st[rng.integers(0, tt.size, 3)] = False
        if r % 9 == 2:
            tt[100] = tt[99]
        t.append(tt), lab.append(np.full(tt.size, r)), static.append(st)
        t0 = tt[-1] + (0.02 if r % 4 == 0 else rng.uniform(1, 100))
    return np.concatenate(t), np.concatenate(lab), np.concatenate(static)


def test_row_runs_choose_the_windows_windows_chooses() -> None:
    """Issue 15: the INS windows chosen from pieces of the static held-out rows, met chunk by chunk, are
    `windows`' on the rows themselves (as campaign positions), for chunks of one row upwards."""
    from labrunner.calibration.ins import RowRuns, windows

    rng = np.random.default_rng(1)
    checked = 0
    for trial in range(6):
        t, lab, static = _static_sequence(rng)
        sel = np.flatnonzero(static & (lab % 3 != 0))  # held-out records' static rows
        idx = windows(t[sel], lab[sel], max_windows=40 if trial % 2 else 400)
        assert idx.size
        want = sel[idx]
        for size in ((1, 333) if trial == 0 else (17, 4096, sel.size)):
            runs = RowRuns()
            for lo in range(0, sel.size, size):
                s = sel[lo:lo + size]
                runs.add(t[s], lab[s], s)
            assert len(runs.pieces()) < sel.size / 100  # a few per record
            got = runs.window_positions(max_windows=40 if trial % 2 else 400)
            assert got is not None
            np.testing.assert_array_equal(got, want)
            checked += 1
    assert checked == 17


def test_row_runs_without_windows_and_when_they_cannot_tell() -> None:
    from labrunner.calibration.ins import RowRuns, windows

    runs = RowRuns()
    runs.add(np.arange(100) * 0.02, np.zeros(100, dtype=np.int64), np.arange(100))
    assert windows(np.arange(100) * 0.02, np.zeros(100)).size == 0
    got = runs.window_positions()
    assert got is not None and got.size == 0
    # A stretch of intervals within the pieces' tolerance of 1.5 x the median interval, some above it and
    # some not: the pieces cannot tell where `windows` breaks (None: the caller gives it the rows).
    dt = np.concatenate([np.full(5000, 0.02), 1.5 * 0.02 * (1 + 1e-8 * np.sin(np.arange(2000)))])
    t = np.concatenate([[0.0], np.cumsum(dt)])
    runs = RowRuns()
    runs.add(t, np.zeros(t.size, dtype=np.int64), np.arange(t.size))
    assert runs.window_positions() is None


def test_windows_navigated_as_their_outputs_come_in_pieces_give_ins_errors_numbers() -> None:
    """The chunked evaluation gives a model's outputs for the INS windows in pieces of INS_CHUNK rows
    (cutting windows): the navigation of each window once its rows are in gives the errors of the whole
    output array, bit for bit."""
    from labrunner.calibration.ins import NAV_WINDOWS, WindowNavigation, ins_errors
    from labrunner.calibration.records import reference_values

    rng = np.random.default_rng(4)
    w, n = 2 * NAV_WINDOWS + 5, 300
    a = {"orientation": np.repeat(rng.integers(0, 6, w), n).astype(np.int8), "rate": np.zeros(w * n)}
    win = rng.permutation(w * n).reshape(w, n)  # windows' rows anywhere in the arrays
    values = reference_values(a["orientation"][win.ravel()], a["rate"][win.ravel()])
    values += rng.normal(0, 1e-3, values.shape) + [1e-3, 0, 0, 0.01, 0, 0]
    want = ins_errors(a, win, {"m": values})["m"]
    assert want.n_windows == w and want.position_m > 0
    # ... which are every window navigated at once (what ins_errors did before it went NAV_WINDOWS at a time)
    from labrunner.calibration.ins import _errors, _solution

    r = reference_values(a["orientation"][win.ravel()], a["rate"][win.ravel()]).reshape(w, n, 6)
    v = values.reshape(w, n, 6)
    dist, ang = _errors(*_solution(v[..., :3], v[..., 3:], 60.0 / n), *_solution(r[..., :3], r[..., 3:], 60.0 / n))
    assert (want.position_m, want.attitude_deg, want.position_m_max) == (dist.mean(), ang.mean(), dist.max())
    nav = WindowNavigation(a, win)
    for size in (1000, n, 7 * n + 11, values.shape[0]):
        got = nav.errors(values[lo:lo + size] for lo in range(0, values.shape[0], size))
        assert got == want
