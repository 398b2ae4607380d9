"""The typed CSV reader and the store's typed frame give what the cell-by-cell text reading gives
(issue 15, target 4), on awkward input; bad cells keep their located one-line messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from labrunner import campaign_csv
from labrunner.campaign_csv import CampaignDataError, read_campaign
from labrunner.data_source import mark_power_ons

HEADER = "t_s,run,orientation,chamber_c,imu_temp_c,table_rate_dps,ax_g,ay_g,az_g,gx_dps,gy_dps,gz_dps"


def _rows(n: int = 6) -> list[str]:
    return [f"{0.02 * i:.2f},1,z_up,{25 + i},{25.5 + i},0,0.01,-0.02,1.0,0.1,0.2,{0.3 + i}" for i in range(n)]


def _text_reference(path: Path) -> pd.DataFrame:
    """Every cell read as text and validated row by row (the reader's fallback, used here directly)."""
    return read_campaign(campaign_csv._read_text(path, str(path)), name=str(path))


def _write(tmp_path: Path, lines: list[str], name: str = "c.csv") -> Path:
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def test_awkward_but_valid_csv_reads_as_the_text_reader_does(tmp_path: Path) -> None:
    rows = _rows()
    rows[1] = rows[1].replace(",z_up,", ", z_up ,").replace(",25.5", ",  25.5")  # spaces around cells
    rows[2] = rows[2].replace(",27,", ",,")  # no chamber reading
    rows[3] = rows[3].replace(",28,", ",nan,")
    rows[4] = rows[4].replace(",1,z_up", ",1.0,x_down")  # a run written as a float
    p = _write(tmp_path, [HEADER + ",power_on,note"] + [r + f",{v},hello" for r, v in
                                                       zip(rows, ["1", "0", "0.0", "true", "False", "1.0"])])
    fast = read_campaign(p)
    ref = _text_reference(p)
    pd.testing.assert_frame_equal(fast, ref)
    assert list(fast.columns)[-1] == "power_on" and fast["power_on"].tolist() == [1, 0, 0, 1, 0, 1]
    assert np.isnan(fast["chamber_c"].iloc[2]) and np.isnan(fast["chamber_c"].iloc[3])
    assert fast["orientation"].tolist()[:2] == ["z_up", "z_up"] and fast["orientation"].iloc[4] == "x_down"


def test_missing_optional_column_and_an_empty_campaign(tmp_path: Path) -> None:
    p = _write(tmp_path, [HEADER] + _rows(3))
    assert "power_on" not in read_campaign(p).columns
    empty = _write(tmp_path, [HEADER], "empty.csv")
    with pytest.raises(CampaignDataError, match=r"empty.csv: no data rows"):
        read_campaign(empty)


@pytest.mark.parametrize(("cell", "column", "message"), [
    ("abc", "az_g", r"c.csv:4: column 'az_g': 'abc' is not a number"),
    ("", "ax_g", r"c.csv:4: column 'ax_g': value missing or not finite"),
    ("up", "orientation", r"c.csv:4: column 'orientation': unknown orientation 'up'"),
    ("1.5", "run", r"c.csv:4: column 'run': '1.5' is not an integer run number"),
])
def test_bad_cells_keep_their_located_messages(tmp_path: Path, cell: str, column: str, message: str) -> None:
    cols = HEADER.split(",")
    rows = [r.split(",") for r in _rows()]
    rows[2][cols.index(column)] = cell
    p = _write(tmp_path, [HEADER] + [",".join(r) for r in rows])
    with pytest.raises(CampaignDataError, match=message):
        read_campaign(p)


def test_bad_power_on_is_located(tmp_path: Path) -> None:
    p = _write(tmp_path, [HEADER + ",power_on"] + [r + ",0" for r in _rows()[:2]] + [_rows()[2] + ",2"])
    with pytest.raises(CampaignDataError, match=r"c.csv:4: column 'power_on': '2' is not 0 or 1"):
        read_campaign(p)


def test_typed_frame_is_validated_without_copies_and_unknown_labels_are_named() -> None:
    frame = read_campaign(pd.DataFrame({
        "t_s": [0.0, 0.1, 0.2], "run": np.array([1, 1, 2]), "chamber_c": 1.0, "imu_temp_c": 2.0,
        "table_rate_dps": 0.0, "ax_g": 0.0, "ay_g": 0.0, "az_g": 1.0, "gx_dps": 0.0, "gy_dps": 0.0, "gz_dps": 0.0,
        "orientation": pd.Categorical.from_codes([0, 0, 6], categories=["x_up", "x_down", "y_up", "y_down", "z_up",
                                                                        "z_down", "sideways"]),
    }).iloc[:2])
    again = read_campaign(frame)
    assert np.shares_memory(again["ax_g"].to_numpy(), frame["ax_g"].to_numpy())
    bad = frame.copy()
    bad["orientation"] = pd.Categorical.from_codes([0, 6], categories=list(frame["orientation"].cat.categories)
                                                   + ["sideways"])
    with pytest.raises(CampaignDataError, match=r"data:1: column 'orientation': unknown orientation 'sideways'"):
        read_campaign(bad)
    back = frame.assign(t_s=[0.2, 0.1])
    with pytest.raises(CampaignDataError, match=r"data:1: column 't_s': time goes backwards within run 1"):
        read_campaign(back)


def test_power_ons_from_events_mark_each_runs_first_row() -> None:
    frame = pd.DataFrame({"run": np.array([1, 1, 2, 2, 2, 3, 3])})
    events = pd.DataFrame({"message": ["powered on (run 1)", "other", "powered on (run 3)"]})
    assert mark_power_ons(frame, events)["power_on"].tolist() == [1, 0, 0, 0, 0, 1, 0]
    back = pd.DataFrame({"run": np.array([1, 2, 1, 3])})  # a run that comes back: its first row only
    assert mark_power_ons(back, events)["power_on"].tolist() == [1, 0, 0, 1]
