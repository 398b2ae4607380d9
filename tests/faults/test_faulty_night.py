"""`labrunner run procedures/quick.yaml --sim --faults 20 --seed 1` finishes like a fault-free run."""

from sqlalchemy import text

from labrunner.store import Store

from ..campaign.conftest import ROOT, cli


def test_quick_with_twenty_random_faults_equals_fault_free(tmp_path):
    clean, faulty = tmp_path / "clean.db", tmp_path / "faulty.db"
    cli("run", ROOT / "procedures" / "quick.yaml", "--sim", "--db", clean, "--quiet", check=0)
    proc = cli("run", ROOT / "procedures" / "quick.yaml", "--sim", "--faults", "20", "--seed", "1", "--db", faulty,
               "--quiet", check=0)
    assert "faults injected: 20" in proc.stderr
    with Store.open_existing(clean) as a, Store.open_existing(faulty) as b:
        sa, sb = a.steps_frame(1), b.steps_frame(1)
        cols = ["idx", "orientation", "temperature_c", "rate_dps", "status", "n_samples"]
        assert sb[cols].equals(sa[cols])
        assert len(b.samples_frame(1)) == len(a.samples_frame(1)) == 192 * 500
        with b.engine.connect() as conn:
            dup = conn.execute(text("SELECT step_idx FROM sample_blocks WHERE kind='record' GROUP BY step_idx "
                                    "HAVING COUNT(*) > 1")).fetchall()
            n_blocks = conn.execute(text("SELECT COUNT(*) FROM sample_blocks WHERE kind='record'")).scalar()
        assert dup == [] and n_blocks == 192
        ev = b.events_frame(1)
    assert (ev.kind == "injected").sum() == 20
    assert (ev.kind == "fault").any() and (ev.kind == "recovery").any()
