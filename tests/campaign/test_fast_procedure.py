"""The shipped paper_campaign_fast in a dry run end to end (issue 16): a shortened copy (two temperatures,
two rates, 5 s records, the shipped soak and fit sections as they are) runs on the simulated lab through
the CLI to a fitted model, every soak decided by the predictive criterion and logged with its decision."""

from __future__ import annotations

import json
import re

from labrunner.store import Store

from .conftest import ROOT, cli


def shortened() -> str:
    text = (ROOT / "procedures" / "paper_campaign_fast.yaml").read_text()
    text = re.sub(r"^temperatures:\n(  .*\n)+", "temperatures: {list_c: [15, 25], order: serpentine}\n", text,
                  flags=re.M)
    text = re.sub(r"^rates:\n(  .*\n)+", "rates: {list_dps: [-50, 50]}\n", text, flags=re.M)
    text = re.sub(r"^record_s: .*$", "record_s: 5", text, flags=re.M)
    text = re.sub(r"^record_poll_s: .*$", "record_poll_s: 5", text, flags=re.M)
    text = re.sub(r"^remount_c: .*$", "remount_c: 23\nremount_s: 30", text, flags=re.M)
    text = text.replace("rbf: true", "rbf: false")
    assert "criterion: predictive" in text
    return text


def test_the_fast_procedure_runs_in_a_dry_run_end_to_end(tmp_path):
    proc = tmp_path / "fast.yaml"
    proc.write_text(shortened())
    db, fit = tmp_path / "fast.db", tmp_path / "fit"
    out = cli("run", proc, "--sim", "--seed", 5, "--db", db, "--fit-out", fit, "--quiet", check=0)
    assert "models written" in out.stderr + out.stdout
    assert (fit / "polynomial.json").exists()
    with Store.open_existing(db) as s:
        assert s.campaign(1).status == "done"
        ev = s.events_frame(1)
        steps = s.steps_frame(1)
    assert len(steps) == 6 * 2 * 2 and (steps.n_samples > 0).all()
    soaked = ev[ev.message.str.startswith("soaked at")]
    assert len(soaked) == 12
    details = [json.loads(d) if isinstance(d, str) else d for d in soaked.detail]
    assert not ev.message.str.contains("falls back").any()
    for d in details:  # the decision, as the issue asks: predicted remaining drift and time constant
        assert d["criterion"] == "predictive" and d["predicted_drift_bound_c"] <= 0.3
        assert 60 < d["tau_s"] < 7200 and d["horizon_s"] == 5.0
    assert ev.message.str.contains("fit stored").any()
