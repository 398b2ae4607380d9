"""The Python API: run campaigns and read what they recorded, as the command line does.

    import labrunner

    result = labrunner.run("procedures/quick.yaml", db="quick.db")       # a dry run on the simulated lab
    with labrunner.open("quick.db") as db:
        campaign = db.campaign()                                         # the latest campaign
        samples = campaign.samples()                                     # pandas, CSV columns + step columns
        fit = campaign.fit()                                             # what `labrunner fit` computes

Every function raises `labrunner.UserError` (with a message naming the file, line or campaign) for
inputs a user can fix. Heavy modules (pandas, the sims, the fitters) are imported when first used,
so `import labrunner` stays fast. See docs/api.md.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labrunner.campaign_session import (
    AbortResult,
    Progress,
    ProgressCallback,
    RunResult,
    Session,
    abort_campaign,
    process_alive,
    start_resume,
    start_run,
)
from labrunner.errors import UserError

if TYPE_CHECKING:
    import pandas as pd

    from labrunner.calibration.fit import FitOptions, FitResult
    from labrunner.data_source import CampaignData
    from labrunner.discrepancy.diagnose import Diagnosis
    from labrunner.lab import LabConfig
    from labrunner.procedure import Procedure
    from labrunner.sims.lab import SimLab
    from labrunner.sims.world import SimLabConfig
    from labrunner.store import CampaignInfo, Store

log = logging.getLogger(__name__)

__all__ = [
    "AbortResult", "Campaign", "CampaignStatus", "Database", "Event", "NextStep", "Progress", "RunResult", "Session",
    "UserError", "abort", "diagnose", "fit", "load_data", "load_lab_config", "load_procedure", "load_sim_config",
    "open", "read_campaign_csv", "resume", "run", "serve_sim", "start_resume", "start_run", "status", "write_fit",
]


# --- running -------------------------------------------------------------------------------------------------


def run(procedure: str | Path | Procedure, *, db: str | Path, lab: str | Path | LabConfig = "sim",
        seed: int | None = None, faults: int = 0, sim_config: str | Path | dict[str, Any] | None = None,
        fit_out: str | Path | None = None, auto_resume: bool = True, progress: ProgressCallback | None = None,
        handle_signals: bool = False) -> RunResult:
    """Run `procedure` (a YAML path or a parsed `Procedure`) as a new campaign stored in `db`.

    `lab="sim"` is a dry run against the simulated lab on a virtual clock (`seed`, `faults` random
    injected faults, `sim_config` a path or mapping); otherwise `lab` is a lab configuration (YAML
    path or `LabConfig`). The end-of-run fit (the procedure's `fit:`) writes its models to `fit_out`
    (default `<db>_fit/` next to the database). `progress` is called with a `Progress` after every
    transition and record. `handle_signals`: Ctrl-C pauses, a second one aborts to the safe state.
    """
    with start_run(procedure, db=db, lab=lab, seed=seed, faults=faults, sim_config=sim_config, fit_out=fit_out,
                   auto_resume=auto_resume) as session:
        return session.execute(progress, handle_signals=handle_signals)


def resume(db: str | Path, *, campaign: int | None = None, lab: str | Path | LabConfig | None = None,
           fit_out: str | Path | None = None, progress: ProgressCallback | None = None,
           handle_signals: bool = False) -> RunResult:
    """Continue a paused, aborted, failed or killed campaign (default: the latest in `db`) from its
    first missing step; a real lab uses the stored lab configuration unless `lab` is given."""
    with start_resume(db, campaign=campaign, lab=lab, fit_out=fit_out) as session:
        return session.execute(progress, handle_signals=handle_signals)


def abort(db: str | Path, *, campaign: int | None = None, wait_s: float = 60.0,
          notify: Callable[[str], None] | None = None) -> AbortResult:
    """Bring a campaign's lab to its safe state (table stopped, chamber to the remount temperature)
    and end the run; it stays resumable. A running process is asked to stop and given `wait_s`;
    with none running, a real lab is made safe from here. `notify` gets progress messages
    (default: logged as warnings)."""
    return abort_campaign(db, campaign=campaign, wait_s=wait_s, notify=notify or log.warning)


# --- status --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Event:
    t_s: float  # campaign time
    kind: str  # transition, record, fault, recovery, interlock, warning, operator, info
    state: str | None
    step_idx: int | None
    message: str


@dataclass(frozen=True)
class NextStep:
    idx: int
    orientation: str
    temperature_c: float
    rate_dps: float


@dataclass(frozen=True)
class CampaignStatus:
    """Progress of a campaign, readable while another process runs it (what `labrunner status` shows)."""

    campaign_id: int
    name: str
    db: Path
    status: str  # running, paused, aborted, failed, done
    process_alive: bool  # a "running" campaign whose process is gone must be resumed
    mode: str  # "sim" or "lab"
    state: str  # the sequencer's last state
    steps_done: int
    steps_total: int
    samples: int
    lab_time_s: float
    next_step: NextStep | None
    eta_s: float | None  # lab time left
    eta_estimated: bool  # from the procedure's estimate (nothing recorded yet), not the pace so far
    updated_wall: float
    faults: int
    rerecorded_steps: int
    recent_events: tuple[Event, ...]

    @property
    def fraction_done(self) -> float:
        return self.steps_done / max(self.steps_total, 1)


def status(db: str | Path, *, campaign: int | None = None, events: int = 8) -> CampaignStatus:
    """The progress of a campaign (default: the latest in `db`) and its `events` most recent events."""
    with open(db) as database:
        return database.campaign(campaign).status_report(events=events)


# --- analysis ------------------------------------------------------------------------------------------------


def read_campaign_csv(path: str | Path) -> pd.DataFrame:
    """A campaign CSV, validated (errors name the file, line and column)."""
    from labrunner.campaign_csv import read_campaign

    return read_campaign(path)


def load_data(data: str | Path, *, campaign: int | None = None, include_monitor: bool = False) -> CampaignData:
    """Validated campaign rows (campaign CSV columns) with provenance, from a CSV or a store."""
    from labrunner.data_source import load_campaign_data

    return load_campaign_data(data, campaign, include_monitor=include_monitor)


def fit(data: str | Path | CampaignData, *, campaign: int | None = None, options: FitOptions | None = None,
        save: bool = True, out: str | Path | None = None, progress: Callable[[str], None] | None = None,
        **overrides: Any) -> FitResult:
    """Fit the calibration models to a campaign (a store's campaign, or a campaign CSV): what
    `labrunner fit` computes. `options` (a `labrunner.calibration.FitOptions`) and `overrides`
    (its fields: `poly_order`, `poly_method`, `rbf_variants`, `rbf_export`, `evaluate`, `splits`,
    `seed`, ...) say what to fit. With a store and `save`, the fit is stored in it with its
    provenance; with `out`, the model files are written there. `progress` gets messages."""
    import dataclasses

    from labrunner.calibration.fit import FitOptions, fit_campaign
    from labrunner.data_source import CampaignData

    try:
        opts = dataclasses.replace(options or FitOptions(), **overrides)
    except TypeError as exc:
        raise UserError(f"fit options: {exc}") from None
    loaded = data if isinstance(data, CampaignData) else load_data(data, campaign=campaign)
    result = fit_campaign(loaded.frame, opts, provenance=loaded.provenance, progress=progress)
    prov = loaded.provenance
    if save and prov.get("kind") == "store":
        from labrunner.store import Store

        with Store.open_existing(prov["source"]) as store:
            fit_id = store.save_fit(int(prov["campaign_id"]), result.to_dict(), result.provenance)
        log.info("fit %d stored in %s (campaign %s)", fit_id, prov["source"], prov["campaign_id"])
        if progress is not None:
            where = prov["source"] if isinstance(data, CampaignData) else data
            progress(f"fit {fit_id} stored in {where} (campaign {prov['campaign_id']})")
    if out is not None:
        write_fit(result, out)
    return result


def write_fit(result: FitResult, out: str | Path, summary: str | None = None) -> list[str]:
    """Write a fit's model JSON files, C header, summary and evaluation tables into `out`; returns the names."""
    from labrunner.calibration.outputs import write_outputs

    return write_outputs(result, Path(out), summary)


def diagnose(data: str | Path | CampaignData | pd.DataFrame, *, campaign: int | None = None,
             **options: Any) -> Diagnosis:
    """What the simulated IMU model gets wrong in measured data (a store's campaign with its monitor
    rows, a campaign CSV, or a frame): what `labrunner diagnose` computes. `options` are
    `labrunner.discrepancy.DiagnoseOptions` fields (`min_evidence`, `causes`, ...)."""
    import pandas as pd

    from labrunner.data_source import CampaignData
    from labrunner.discrepancy.diagnose import DiagnoseOptions
    from labrunner.discrepancy.diagnose import diagnose as run_diagnosis

    try:
        opts = DiagnoseOptions(**options)
    except TypeError as exc:
        raise UserError(f"diagnose options: {exc}") from None
    if isinstance(data, pd.DataFrame):
        frame = data
    else:
        # Ramps and soaks too: thermal lag and hysteresis show there.
        frame = (data if isinstance(data, CampaignData) else load_data(data, campaign=campaign,
                                                                       include_monitor=True)).frame
    return run_diagnosis(frame, opts)


# --- inputs and the simulated lab ---------------------------------------------------------------------------


def load_procedure(path: str | Path) -> Procedure:
    """A validated procedure (errors name the file, line and key)."""
    from labrunner.procedure import load_procedure as load

    return load(path)


def load_lab_config(path: str | Path) -> LabConfig:
    """A validated lab configuration (the instruments and their addresses)."""
    from labrunner.lab import load_lab_config as load

    return load(path)[0]


def load_sim_config(source: str | Path | dict[str, Any] | None) -> SimLabConfig:
    """A validated sim configuration (seed, plants, IMU model, faults) from a path or a mapping."""
    from labrunner.sim_config import load_sim_config as load

    return load(source)


def serve_sim(*, config: str | Path | dict[str, Any] | None = None, speed: float = 1.0, host: str = "127.0.0.1",
              link: str = "tcp", chamber_transport: str = "tcp", profile: str = "watlow_f4",
              ports: tuple[int, int, int] = (0, 0, 0)) -> SimLab:
    """The simulated chamber, rate table and IMU as servers (`labrunner sim serve`), on a clock
    `speed` times faster than wall time; `ports` (chamber, table, IMU), 0 for any free port.
    Close the returned `SimLab` to stop them; `.lab_config()` is a lab configuration pointing at them."""
    from labrunner.clock import ScaledClock
    from labrunner.sims.lab import SimLab, SimPorts

    if speed <= 0:
        raise UserError("--speed must be > 0")
    sim_config = load_sim_config(config)
    try:
        lab = SimLab(sim_config, ScaledClock(speed), host=host, link=link, chamber_transport=chamber_transport,
                     chamber_profile=profile, ports=SimPorts(chamber=ports[0], table=ports[1], imu=ports[2]))
    except OSError as exc:
        raise UserError(f"cannot start the simulated lab: {exc}") from None
    log.info("simulated lab serving on %s at %gx", host, speed)
    return lab


# --- reading a store -----------------------------------------------------------------------------------------


def open(db: str | Path) -> Database:  # noqa: A001 - `labrunner.open(db)`, as `sqlite3.connect`/`h5py.File`
    """Open a labrunner store for reading (a context manager; also usable while a campaign runs)."""
    from labrunner.store import Store

    return Database(Store.open_existing(db))


class Database:
    """A labrunner SQLite store: one or more campaigns."""

    def __init__(self, store: Store) -> None:
        self.store = store

    @property
    def path(self) -> Path:
        return self.store.path

    def campaigns(self) -> list[Campaign]:
        return [Campaign(self, cid) for cid in self.store.campaign_ids()]

    def campaign(self, id: int | None = None) -> Campaign:  # noqa: A002 - the campaign's id, as in the store
        """The campaign `id`, or the latest one in the file."""
        return Campaign(self, self.store.resolve(id))

    def close(self) -> None:
        self.store.close()

    def __enter__(self) -> Database:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<labrunner.Database {self.path} campaigns={self.store.campaign_ids()}>"


class Campaign:
    """One campaign of a store: what was planned, recorded and logged, and the analyses of it."""

    def __init__(self, db: Database, campaign_id: int) -> None:
        self.db = db
        self.id = campaign_id

    @property
    def _store(self) -> Store:
        return self.db.store

    @property
    def info(self) -> CampaignInfo:
        """The campaign row (procedure text and hash, lab and sim configuration, status, ...), read now."""
        return self._store.campaign(self.id)

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def status(self) -> str:
        return self.info.status

    def procedure(self) -> Procedure:
        """The procedure the campaign was planned from (as stored with it)."""
        from labrunner.procedure import parse_procedure

        return parse_procedure(self.info.procedure_text, f"{self.db.path} (campaign {self.id} procedure)")

    def steps(self) -> pd.DataFrame:
        """The planned record steps: idx, orientation, temperature_c, rate_dps, status, attempts, n_samples, ..."""
        return self._store.steps_frame(self.id)

    def events(self) -> pd.DataFrame:
        """Every event (transitions, records, faults, recoveries, operator actions) in order; `detail` decoded."""
        frame = self._store.events_frame(self.id)
        frame["detail"] = [json.loads(d) if isinstance(d, str) and d else None for d in frame["detail"]]
        return frame

    def samples(self, include_monitor: bool = False) -> pd.DataFrame:
        """Samples in the campaign CSV columns, time-ordered, with per row `kind` (record/monitor), the
        sequencer's `state`, the `step_idx` of its step, the chamber `setpoint_c` and the commanded
        table rate `rate_cmd_dps`. Monitor rows (1 s means while the chamber moves to the remount
        temperature or a step's, and soaks there) only with `include_monitor`."""
        return self._store.samples_frame(self.id, include_monitor=include_monitor, with_steps=True,
                                         remount_c=self.procedure().model.remount_c)

    def data(self, include_monitor: bool = False) -> CampaignData:
        """Validated samples (campaign CSV columns) with provenance: what `fit` and `diagnose` read."""
        return self._store.campaign_data(self.id, include_monitor=include_monitor)

    def fits(self) -> pd.DataFrame:
        """Fits stored with the campaign (by `labrunner fit` or the end-of-run fit)."""
        return self._store.fits_frame(self.id)

    def fit(self, *, options: FitOptions | None = None, save: bool = True, out: str | Path | None = None,
            progress: Callable[[str], None] | None = None, **overrides: Any) -> FitResult:
        """Fit the calibration models to the recorded steps, stored with the campaign unless
        `save=False` (see `labrunner.fit`)."""
        return fit(self.data(), options=options, save=save, out=out, progress=progress, **overrides)

    def diagnose(self, **options: Any) -> Diagnosis:
        """Diagnose the simulated IMU model against this campaign, monitor rows included (see `labrunner.diagnose`)."""
        return diagnose(self.data(include_monitor=True), **options)

    def export_csv(self, path: Any, include_monitor: bool = False) -> int:
        """Write the campaign CSV format (a path or a text stream); returns the number of rows."""
        from labrunner.campaign_csv import write_campaign

        frame = self._store.samples_frame(self.id, include_monitor=include_monitor)
        if frame.empty:
            raise UserError(f"{self.db.path}: campaign {self.id} has no recorded samples to export")
        write_campaign(frame, path)
        return len(frame)

    def status_report(self, events: int = 8) -> CampaignStatus:
        """Progress, state, ETA and recent events (see `labrunner.status`)."""
        store = self._store
        info = store.campaign(self.id)
        stp = store.steps_frame(self.id)
        recent = store.events_frame(self.id, last=events)
        trans = store.events_frame(self.id)
        done = int((stp.status == "done").sum())
        total = len(stp)
        is_transition = trans.kind == "transition"
        state = str(trans[is_transition].state.iloc[-1]) if is_transition.any() else "idle"
        lab_time = info.clock_last - info.clock_t0
        pending = stp[stp.status != "done"]
        nxt, eta, estimated = None, None, False
        if not pending.empty:
            row = pending.iloc[0]
            nxt = NextStep(int(row.idx), str(row.orientation), float(row.temperature_c), float(row.rate_dps))
            if done:
                eta = lab_time / done * (total - done)  # at the pace so far
            else:
                eta, estimated = self.procedure().estimated_duration_s(), True
        return CampaignStatus(
            campaign_id=self.id, name=info.name, db=self.db.path, status=info.status,
            process_alive=process_alive(info.pid, info.host), mode=info.mode, state=state, steps_done=done,
            steps_total=total, samples=int(stp.n_samples.fillna(0).sum()), lab_time_s=lab_time, next_step=nxt,
            eta_s=eta, eta_estimated=estimated, updated_wall=info.updated_wall,
            faults=int(trans.kind.isin(["fault", "interlock"]).sum()), rerecorded_steps=int((stp.attempts > 1).sum()),
            recent_events=tuple(Event(float(e.t_s), str(e.kind), None if e.state is None else str(e.state),
                                      None if e.step_idx is None or e.step_idx != e.step_idx else int(e.step_idx),
                                      str(e.message)) for e in recent.itertuples()))

    def __repr__(self) -> str:
        info = self.info
        return f"<labrunner.Campaign {self.id} '{info.name}' {info.status} in {self.db.path}>"
