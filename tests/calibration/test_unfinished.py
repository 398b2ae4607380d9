"""A fit of a campaign paused after one orientation says so: stderr, summary.md, model JSON and C header."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import labrunner
from labrunner.cli import main
from tests.campaign.conftest import TINY as CAMPAIGN_TINY

# The campaign tests' tiny procedure with 10 s records (a calibration record is at least 5 s).
TINY = CAMPAIGN_TINY.replace("record_s: 4", "record_s: 10")
assert "record_s: 10" in TINY


@pytest.fixture(scope="module")
def paused(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("paused")
    (d / "tiny.yaml").write_text(TINY)
    with labrunner.start_run(d / "tiny.yaml", db=d / "p.db") as session:
        def pause_after_one_orientation(progress: labrunner.Progress) -> None:
            if progress.steps_done == 6:  # 2 temperatures x 3 rates: x_up recorded, nothing else
                session.request_pause("test: pause after one orientation")

        assert session.execute(pause_after_one_orientation).state == "paused"
    return d / "p.db"


def test_fit_of_a_paused_campaign_says_it_is_unfinished(paused: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "fit"
    assert main(["fit", str(paused), "--out", str(out), "--no-store", "--quiet", "--splits", "random"]) == 0
    err = capsys.readouterr().err
    assert "warning: unfinished campaign: 6 of 36 planned steps recorded (status paused)" in err
    assert "Unfinished campaign:" in (out / "summary.md").read_text()
    header = (out / "imu_calibration.h").read_text()
    head = header[:header.index("#ifndef")]
    assert "6 of 36 planned steps recorded" in head and "WARNING: unfinished campaign" in head
    assert "not fitted: accel:" in head or "fitted in combination: accel:" in head
    for name in ("polynomial.json", "rbf.json"):
        if (out / name).exists():
            prov = json.loads((out / name).read_text())["provenance"]
            assert prov["steps_recorded"] == 6 and prov["steps_planned"] == 36
            assert prov["unfinished"].startswith("unfinished campaign") and prov["not_fitted"]
