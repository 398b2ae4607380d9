"""`labrunner diagnose`: end to end on a CSV, and clear errors for bad data (never a traceback)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labrunner.campaign_csv import write_campaign
from labrunner.cli import main
from labrunner.sims.world import SimLabConfig

from .campaigns import DRAWS, campaign
from .test_hidden_effects import case_seed


@pytest.fixture(scope="module")
def campaign_csv(tmp_path_factory):
    seed = case_seed("cli")
    hidden = DRAWS["hysteresis"](np.random.default_rng(seed))
    frame, _ = campaign([hidden], "sims", seed)
    path = tmp_path_factory.mktemp("cli") / "campaign.csv"
    write_campaign(frame, path)
    return path, hidden


def test_diagnose_writes_json_model_and_report(campaign_csv, tmp_path, capsys):
    path, hidden = campaign_csv
    out = tmp_path / "diagnosis.json"
    report = tmp_path / "report"
    assert main(["diagnose", str(path), "--json", str(out), "--report", str(report)]) == 0
    printed = capsys.readouterr().out
    assert "verdict: hysteresis" in printed

    doc = json.loads(out.read_text())
    assert doc["verdict"] == "hysteresis"
    finding = doc["findings"][0]
    assert set(finding) >= {"cause", "channels", "parameters", "gain", "confounded_with", "evidence"}
    assert set(finding["gain"]) >= {"heldout_rms_before", "heldout_rms_after", "improvement_pct"}
    assert set(finding["parameters"]["width"]) == hidden.channels
    assert isinstance(doc["not_identifiable"], list)
    assert doc["data"]["kind"] == "csv"

    model_path = doc["extended_model"]["path"]
    config = SimLabConfig.from_dict({"imu_model": model_path})
    assert "hysteresis" in config.imu_model.effects

    for name in ("summary.md", "residuals.csv", "residual_vs_temperature.png", "residual_vs_temperature_rate.png",
                 "residual_vs_time_since_power_on.png", "residual_by_run.png", "residual_vs_table_rate.png",
                 "heldout_rms.png"):
        assert (report / name).stat().st_size > 0, name
    # One power-on per orientation: the run figure stands for both (see test_report_plots).
    assert not (report / "residual_by_orientation.png").exists()
    assert "hysteresis" in (report / "summary.md").read_text()


def _broken(path, tmp_path, edit):
    lines = path.read_text().splitlines()
    lines = edit(lines)
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    return bad


def _header_index(lines, column):
    return lines[0].split(",").index(column)


def _set(lines, line_no, column, value):
    cells = lines[line_no - 1].split(",")
    cells[_header_index(lines, column)] = value
    lines[line_no - 1] = ",".join(cells)
    return lines


@pytest.mark.parametrize("edit, expected", [
    (lambda ls: [",".join(c for c in ls[0].split(",") if c != "gy_dps")]
     + [",".join(v for i, v in enumerate(row.split(",")) if i != _header_index(ls, "gy_dps")) for row in ls[1:]],
     ["missing column(s) gy_dps"]),
    (lambda ls: _set(ls, 57, "gx_dps", "nan"), [":57:", "column 'gx_dps'", "NaN"]),
    (lambda ls: _set(ls, 123, "t_s", "0.5"), [":123:", "column 't_s'", "time goes backwards"]),
    (lambda ls: _set(ls, 200, "orientation", "q_up"), [":200:", "column 'orientation'", "unknown orientation 'q_up'"]),
    (lambda ls: _set(ls, 31, "ax_g", "fast"), [":31:", "column 'ax_g'", "'fast' is not a number"]),
], ids=["missing column", "nan", "time backwards", "unknown orientation", "not a number"])
def test_bad_data_gives_a_clear_error_naming_row_and_column(campaign_csv, tmp_path, capsys, edit, expected):
    path, _ = campaign_csv
    bad = _broken(path, tmp_path, edit)
    code = main(["diagnose", str(bad), "--json", str(tmp_path / "out.json")])
    err = capsys.readouterr().err
    assert code != 0
    assert "Traceback" not in err
    assert str(bad) in err
    for text in expected:
        assert text in err
    assert not (tmp_path / "out.json").exists()


def test_missing_file_and_unknown_cause_are_user_errors(campaign_csv, tmp_path, capsys):
    assert main(["diagnose", str(tmp_path / "nope.csv"), "--json", str(tmp_path / "o.json")]) == 2
    assert "file not found" in capsys.readouterr().err
    path, _ = campaign_csv
    assert main(["diagnose", str(path), "--json", str(tmp_path / "o.json"), "--causes", "gremlins"]) == 2
    assert "unknown cause(s) gremlins" in capsys.readouterr().err


def test_too_little_data_is_a_user_error(campaign_csv, tmp_path, capsys):
    path, _ = campaign_csv
    short = _broken(path, tmp_path, lambda ls: ls[:30])
    assert main(["diagnose", str(short), "--json", str(tmp_path / "o.json")]) == 2
    assert "too little data" in capsys.readouterr().err
