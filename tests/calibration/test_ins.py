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
