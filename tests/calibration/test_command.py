"""`labrunner fit` end to end on a CSV."""

from __future__ import annotations

import json

import pytest

from labrunner.campaign_csv import write_campaign
from labrunner.cli import main

from calib_campaigns import make_campaign


@pytest.fixture(scope="module")
def csv_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("fit") / "campaign.csv"
    write_campaign(make_campaign(seed=41, temperatures_c=(-20.0, 0.0, 20.0, 40.0, 55.0), average_s=2.0), path)
    return path


def test_fit_writes_json_models_header_and_tables(csv_path, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["fit", str(csv_path), "--json", str(tmp_path / "fit.json"), "--out", str(out)])
    assert rc == 0
    cap = capsys.readouterr()
    assert "# Calibration fit" in cap.out and "Polynomial model" in cap.out and "Improvement (%)" in cap.out
    assert "evaluation: random" in cap.err  # progress on stderr
    data = json.loads((tmp_path / "fit.json").read_text())
    prov = data["provenance"]
    assert prov["kind"] == "csv" and prov["source"].endswith("campaign.csv") and prov["rows"] > 0
    assert prov["software"]["name"] == "labrunner" and prov["software"]["version"]
    assert data["data"]["time_range_s"][1] > data["data"]["time_range_s"][0]
    assert len(data["data"]["temperature_steps"]) == 5
    assert data["models"]["polynomial"]["accel"]["temperature_range_c"][0] < -15
    assert data["models"]["rbf"]["variant"] == "hybrid"
    assert {e["name"] for e in data["evaluation"]} >= {"random", "between_temperatures", "beyond_temperatures"}
    for name in ("polynomial.json", "rbf.json", "imu_calibration.h", "summary.md", "evaluation.csv"):
        assert (out / name).stat().st_size > 0
    assert "lr_poly_compensate" in (out / "imu_calibration.h").read_text()


def test_fit_options_and_errors(csv_path, tmp_path, capsys):
    rc = main(["fit", str(csv_path), "--no-eval", "--order", "cv", "--rbf", "paper", "--quiet",
               "--json", str(tmp_path / "f.json")])
    assert rc == 0
    data = json.loads((tmp_path / "f.json").read_text())
    # the paper's network sees raw outputs: its measured gain departs from the fitted scale, so it is not
    # exported, and stderr, the JSON and its gains say why
    assert data["evaluation"] == [] and "rbf" not in data["models"]
    assert not data["gains"]["rbf_paper"]["passed"] and data["gains"]["polynomial"]["passed"]
    assert "rbf_paper" in data["not_exported"][0] and "gain departs" in data["not_exported"][0]
    assert "warning: the RBF network `rbf_paper`" in capsys.readouterr().err
    assert data["models"]["polynomial"]["gyro"]["cv_scores"]
    assert main(["fit", str(tmp_path / "missing.csv")]) == 2
    assert "file not found" in capsys.readouterr().err
    assert main(["fit", str(csv_path), "--order", "cubic"]) == 2
    assert "--order" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text(csv_path.read_text().replace("x_up", "sideways", 1))
    assert main(["fit", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "sideways" in err and "Traceback" not in err


def test_library_entry_without_networks_writes_outputs(csv_path, tmp_path):
    """What the sequencer's end-of-campaign hook calls: fit_campaign, to_dict, write_outputs."""
    from labrunner.calibration.command import write_outputs
    from labrunner.calibration.fit import FitOptions, fit_campaign
    from labrunner.data_source import load_campaign_data

    data = load_campaign_data(csv_path)
    result = fit_campaign(data.frame, FitOptions(rbf_variants=(), rbf_export="", splits=("random",)),
                          provenance=data.provenance)
    assert result.rbf is None and "rbf" not in result.to_dict()["models"]
    json.dumps(result.to_dict(), allow_nan=False)
    written = write_outputs(result, tmp_path / "o")
    assert "rbf.json" not in written and (tmp_path / "o" / "imu_calibration.h").exists()
    assert "lr_rbf_compensate" not in (tmp_path / "o" / "imu_calibration.h").read_text()
