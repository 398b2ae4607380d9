"""`labrunner compensate MODEL DATA --csv FILE` end to end: from a fit's model files to compensated rows."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from field_logs import field_log

import labrunner
from labrunner.calibration.compensation import compensate
from labrunner.calibration.export import load_model
from labrunner.cli import main
from tests.campaign.conftest import TINY as CAMPAIGN_TINY

OUT = ["ax_g", "ay_g", "az_g", "gx_dps", "gy_dps", "gz_dps"]


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 24 h field log (8 h per power-on: ramps of 0.08 C/min) and the models of a fit to its rows below 20 C."""
    d = tmp_path_factory.mktemp("comp")
    frame, _ = field_log(seed=3, hours_per_run=8.0)
    frame.to_csv(d / "log.csv", index=False, float_format="%.9g", na_rep="")
    frame[frame.imu_temp_c < 20.0].to_csv(d / "cool.csv", index=False, float_format="%.9g", na_rep="")
    assert main(["fit", str(d / "cool.csv"), "--out", str(d / "fit"), "--no-eval", "--quiet",
                 "--json", str(d / "fit.json")]) == 0
    return d


def test_compensate_a_csv_with_each_model_file(fitted: Path, capsys) -> None:
    for model_file in ("polynomial.json", "rbf.json", "../fit.json"):
        out = fitted / f"comp-{Path(model_file).stem}.csv"
        assert main(["compensate", str(fitted / "fit" / model_file), str(fitted / "log.csv"), "--csv", str(out)]) == 0
        err = capsys.readouterr().err
        assert "rows compensated with" in err and "flagged as extrapolation" in err
        raw = pd.read_csv(fitted / "log.csv")
        got = pd.read_csv(out)
        assert len(got) == len(raw) and list(got.columns[:12]) == list(raw.columns)
        model = load_model(fitted / "fit" / ("rbf.json" if model_file != "polynomial.json" else model_file))
        want = compensate(model, raw[OUT].to_numpy(), raw["imu_temp_c"].to_numpy())
        assert np.allclose(got[[c + "_comp" for c in OUT]].to_numpy(), want.values, rtol=1e-7, atol=1e-9)
        # rows hotter than the fit's data are flagged, not refused
        hot = raw["imu_temp_c"].to_numpy() > 20.5
        assert hot.any() and got["extrapolated"].to_numpy()[hot].all()
        t = raw["imu_temp_c"].to_numpy()
        assert not got["extrapolated"].to_numpy()[(t > 6.0) & (t < 19.0)].any()


def test_compensate_errors_are_one_located_line(fitted: Path, tmp_path: Path, capsys) -> None:
    log = str(fitted / "log.csv")
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"format": "labrunner-diagnosis/1", "findings": []}))
    assert main(["compensate", str(other), log, "--csv", str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err
    assert "other.json: format 'labrunner-diagnosis/1' is not a labrunner calibration model" in err
    broken = tmp_path / "broken.json"
    broken.write_text('{"format": "labrunner-calibration-model/1",\n "model": ')
    assert main(["compensate", str(broken), log, "--csv", str(tmp_path / "o.csv")]) == 2
    assert "broken.json:2: not JSON" in capsys.readouterr().err
    cut = tmp_path / "cut.csv"
    pd.read_csv(log).drop(columns=["gz_dps"]).to_csv(cut, index=False)
    assert main(["compensate", str(fitted / "fit" / "rbf.json"), str(cut), "--csv", str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err
    assert "cut.csv:1: missing column(s) gz_dps" in err and "Traceback" not in err
    assert main(["compensate", str(fitted / "fit" / "rbf.json"), log, "--csv", log]) == 2  # the input itself
    assert "Traceback" not in capsys.readouterr().err


# The campaign tests' tiny procedure with 10 s records (a calibration record is at least 5 s), the end-of-run fit on.
TINY = CAMPAIGN_TINY.replace("record_s: 4", "record_s: 10").replace("fit: {run: false}\n", "")
assert "record_s: 10" in TINY


def test_compensate_a_dry_runs_store(tmp_path: Path, capsys) -> None:
    (tmp_path / "tiny.yaml").write_text(TINY)
    fit_dir = tmp_path / "fit"
    assert labrunner.run(tmp_path / "tiny.yaml", db=tmp_path / "t.db", fit_out=fit_dir).state == "done"
    out = tmp_path / "comp.csv"
    assert main(["compensate", str(fit_dir / "polynomial.json"), str(tmp_path / "t.db"), "--csv", str(out)]) == 0
    got = pd.read_csv(out)
    assert len(got) > 0 and {c + "_comp" for c in OUT} <= set(got.columns)
    # compensation brings static accelerometer rows closer to 1 g than they were
    static = got["table_rate_dps"].abs() < 0.05
    raw_norm = np.linalg.norm(got.loc[static, OUT[:3]].to_numpy(), axis=1)
    comp_norm = np.linalg.norm(got.loc[static, [c + "_comp" for c in OUT[:3]]].to_numpy(), axis=1)
    assert np.abs(comp_norm - 1).mean() < np.abs(raw_norm - 1).mean()
