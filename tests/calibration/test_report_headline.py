"""The headline of `labrunner fit`: the exported model and its held-out gain come first, and its numbers
are those of the fit (JSON) and of the tables below it."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from labrunner.campaign_csv import write_campaign
from labrunner.cli import main

from calib_campaigns import make_campaign

GAIN_LINE = re.compile(r"^- (accelerometer|gyroscope): (\S+) (g|deg/s) raw -> (\S+) \3: gain (\S+) % over raw"
                       r"(?:, (\S+) % over the polynomial \((\S+) \3\))?")


@pytest.fixture(scope="module")
def csv_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("headline") / "campaign.csv"
    write_campaign(make_campaign(seed=43, temperatures_c=(-20.0, 0.0, 20.0, 40.0, 55.0), average_s=2.0), path)
    return path


def _fit(csv_path, tmp_path, capsys, *args: str) -> tuple[list[str], dict]:
    out = tmp_path / "fit.json"
    assert main(["fit", str(csv_path), "--quiet", "--no-store", "--json", str(out), *args]) == 0
    return capsys.readouterr().out.splitlines(), json.loads(out.read_text())


def _triad_rms(split: dict, model: str, triad: str) -> float:
    rms = [v for k, v in split["samples"][model]["rms"].items() if k.startswith(triad)]
    return float(np.sqrt(np.mean(np.square(rms))))


def test_headline_names_the_exported_model_and_its_held_out_gain(csv_path, tmp_path, capsys):
    lines, data = _fit(csv_path, tmp_path, capsys)
    assert lines[0] == "# Calibration fit"
    head = lines[:12]
    first_table = next(i for i, ln in enumerate(lines) if ln.startswith("|"))
    exported = next(i for i, ln in enumerate(head) if ln.startswith("**Exported**"))
    assert exported < first_table
    assert "`rbf_hybrid`" in head[exported] and "imu_calibration.h" in head[exported]
    assert data["models"]["rbf"]["variant"] == "hybrid"
    gain = next(ln for ln in head if ln.startswith("**Held-out gain**"))
    assert "`between_temperatures` split" in gain
    split = next(s for s in data["evaluation"] if s["name"] == "between_temperatures")
    triads = {"accelerometer": "accel", "gyroscope": "gyro"}
    found = [m for m in map(GAIN_LINE.match, head) if m]
    assert [m.group(1) for m in found] == ["accelerometer", "gyroscope"]
    glance = {tuple(c.strip() for c in ln.strip("|").split("|"))[:2]: [c.strip() for c in ln.strip("|").split("|")]
              for ln in lines if ln.startswith("| between_temperatures")}
    for m in found:
        triad = triads[m.group(1)]
        raw, poly, model = (_triad_rms(split, k, triad) for k in ("raw", "polynomial", "rbf_hybrid"))
        # The quoted numbers are the fit's, rounded as printed ...
        assert m.group(2) == f"{raw:.3g}" and m.group(4) == f"{model:.3g}" and m.group(7) == f"{poly:.3g}"
        assert float(m.group(5)) == pytest.approx(100 * (1 - model / raw), abs=0.006)
        assert float(m.group(6)) == pytest.approx(100 * (1 - model / poly), abs=0.006)
        # ... and the same as in the table that follows.
        row = glance[("between_temperatures", f"{triad} ({m.group(3)})")]
        # PX4's method: the reference column, with the gain over it; "-" where it does not apply (soaks)
        px4 = (f"{_triad_rms(split, 'px4', triad):.3g}", f"{100 * (1 - model / _triad_rms(split, 'px4', triad)):.2f}") \
            if "px4" in split["samples"] else ("-", "-")
        assert row[2:] == [m.group(2), m.group(7), m.group(4), px4[0], m.group(5), m.group(6), px4[1]]
    not_fitted = next(ln for ln in head if ln.startswith("**Not fitted:**"))
    for item in data["not_fitted"]:
        assert item in not_fitted
    assert "between_rates" in not_fitted or not data["not_fitted"]


def test_headline_without_a_network_or_an_evaluation(csv_path, tmp_path, capsys):
    lines, data = _fit(csv_path, tmp_path, capsys, "--rbf", "", "--no-eval")
    head = "\n".join(lines[:8])
    assert "no RBF network was trained" in head and "`lr_poly_compensate`" in head
    assert "**Held-out gain:** not measured: no evaluation ran (--no-eval)." in head
    assert "over the polynomial" not in head and "models" in data and "rbf" not in data["models"]
