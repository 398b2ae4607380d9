"""A labrunner store read from Python: `Database` (campaigns) and `Campaign` (its plan, samples,
events, fits, status), as frames and dataclasses; readable while another process runs a campaign.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labrunner.campaign_analysis import diagnose, fit
from labrunner.errors import UserError
from labrunner.output_paths import check_output
from labrunner.store_address import StoreAddress, store_address

if TYPE_CHECKING:
    import pandas as pd

    from labrunner.calibration.fit import FitOptions, FitResult
    from labrunner.data_source import CampaignData
    from labrunner.discrepancy.diagnose import Diagnosis
    from labrunner.procedure import Procedure
    from labrunner.runner.soak import SoakProgress
    from labrunner.store import CampaignInfo, Store

log = logging.getLogger(__name__)


def process_alive(pid: int | None, host: str | None, heartbeat_wall: float | None = None) -> bool:
    """Whether the process that last ran a campaign is still alive: on this host, its pid exists; on
    another host (where no pid can be looked at) its lease's heartbeat is fresh (`runner.lease`)."""
    from labrunner.runner.lease import holder_alive

    if host != os.uname().nodename and heartbeat_wall is None:
        return False
    return holder_alive(pid, host, heartbeat_wall)


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
    db: StoreAddress  # str() shows a URL's password masked
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
    chamber_c: float | None = None  # the latest stored chamber reading
    imu_temp_c: float | None = None  # the latest stored IMU temperature (a record's or a monitor mean)
    soak: SoakProgress | None = None  # while soaking: from the monitor means stored since the soak began
    eta_wall_s: float | None = None  # wall time to the last step at this session's measured pace

    @property
    def fraction_done(self) -> float:
        return self.steps_done / max(self.steps_total, 1)

    @property
    def over(self) -> bool:
        """Nothing runs it any more: it ended (done, paused, aborted, failed) or its process is gone."""
        return self.status != "running" or not self.process_alive


@dataclass(frozen=True)
class CampaignSummary:
    """One campaign of a store as `labrunner list` shows it, read in one query."""

    campaign_id: int
    name: str
    status: str  # running, paused, aborted, failed, done
    mode: str  # "sim" or "lab"
    steps_done: int
    steps_total: int
    samples: int  # in the recorded steps
    pid: int | None  # the process running it (stored while it runs; cleared when it ends)
    host: str | None
    process_alive: bool | None  # of a running campaign: None when it runs on another host (unknowable here)
    heartbeat_wall: float  # wall time of the last heartbeat or status change
    heartbeat_age_s: float  # its age when read
    lease_held: bool = False  # a process holds the campaign's lease (runner.lease): pid/host name it

    @property
    def holder(self) -> str | None:
        """Who holds a running campaign (or its lease), e.g. "pid 4242 on lab-pc" (None otherwise)."""
        if (self.status != "running" and not self.lease_held) or self.pid is None:
            return None
        return f"pid {self.pid} on {self.host or '?'}"


def open_database(db: str | Path | StoreAddress) -> Database:
    """Open a labrunner store for reading (a context manager; also usable while a campaign runs): a
    SQLite file's path, or a URL (`postgresql+psycopg://user@host:port/dbname`, `sqlite:///path`)."""
    from labrunner.store import Store

    address = store_address(db)
    path = address.file
    # SQLite would make an empty file a database (WAL mode writes a header). Only stat, not read: a
    # descriptor closed here would drop the SQLite locks of a store this process has open.
    if path is not None and path.is_file() and path.stat().st_size == 0:
        raise UserError(f"{path}: not a labrunner database (an empty file)")
    return Database(Store.open_existing(address))


class Database:
    """A labrunner store (a SQLite file or a PostgreSQL database): one or more campaigns."""

    def __init__(self, store: Store) -> None:
        self.store = store

    @property
    def path(self) -> StoreAddress:
        """Where the store is (a file's path, or a URL shown with its password masked)."""
        return self.store.path

    def campaigns(self) -> list[Campaign]:
        return [Campaign(self, cid) for cid in self.store.campaign_ids()]

    def summaries(self) -> list[CampaignSummary]:
        """Every campaign with its status, progress, mode, holder and last heartbeat (`labrunner list`)."""
        import time

        from sqlalchemy import case, func, select

        from labrunner.store import campaigns, steps

        done = func.coalesce(func.sum(case((steps.c.status == "done", 1), else_=0)), 0)
        samples = func.coalesce(func.sum(case((steps.c.status == "done", steps.c.n_samples), else_=0)), 0)
        query = (select(campaigns.c.id, campaigns.c.name, campaigns.c.status, campaigns.c.mode, campaigns.c.n_steps,
                        campaigns.c.pid, campaigns.c.host, campaigns.c.updated_wall, campaigns.c.lease_token,
                        campaigns.c.lease_wall, done.label("done"),
                        samples.label("samples"))
                 .select_from(campaigns.outerjoin(steps, steps.c.campaign_id == campaigns.c.id))
                 .group_by(campaigns.c.id).order_by(campaigns.c.id))
        # One query for the whole store: a paper campaign has 4080 steps, a store may hold many.
        with self.store.engine.connect() as conn:
            rows = conn.execute(query).all()
        now = time.time()
        here = os.uname().nodename
        return [CampaignSummary(
            campaign_id=int(r.id), name=str(r.name), status=str(r.status), mode=str(r.mode), steps_done=int(r.done),
            steps_total=int(r.n_steps), samples=int(r.samples), pid=r.pid, host=r.host,
            process_alive=(process_alive(r.pid, r.host) if r.status == "running" and r.host == here else None),
            heartbeat_wall=float(r.updated_wall), heartbeat_age_s=max(0.0, now - float(r.updated_wall)),
            lease_held=r.lease_token is not None)
            for r in rows]

    def summary(self) -> pd.DataFrame:
        """`summaries()` as a frame, one row per campaign: the `CampaignSummary` fields and `holder`."""
        import dataclasses

        import pandas as pd

        names = [f.name for f in dataclasses.fields(CampaignSummary)]
        rows = self.summaries()
        frame = pd.DataFrame([dataclasses.astuple(s) for s in rows], columns=names).astype({"pid": "Int64"})
        frame["holder"] = pd.Series([s.holder for s in rows], dtype=object)
        return frame

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

        return parse_procedure(self.info.procedure_text, f"{self.db.path} (campaign {self.id} procedure)",
                               stored=True)

    def steps(self) -> pd.DataFrame:
        """The planned record steps: idx, orientation, temperature_c, rate_dps, status, attempts, n_samples, ..."""
        return self._store.steps_frame(self.id)

    def events(self) -> pd.DataFrame:
        """Every event (transitions, records, faults, recoveries, operator actions) in order; `detail` decoded."""
        frame = self._store.events_frame(self.id)
        frame["detail"] = [self._detail(d, step) for d, step in zip(frame["detail"], frame["step_idx"])]
        return frame

    def _detail(self, value: Any, step: Any) -> Any:
        """An event's JSON detail, or `StoreDamage` naming campaign, table and step when it is not JSON."""
        if not isinstance(value, str) or not value:
            return None
        try:
            return json.loads(value)
        except ValueError as exc:
            from labrunner.store import StoreDamage

            at = "" if step is None or step != step else f", step {int(step)}"
            raise StoreDamage(f"{self.db.path}: campaign {self.id}, table events{at}: column detail is not JSON "
                              f"({exc}); the store is damaged") from None

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
            force: bool = False, progress: Callable[[str], None] | None = None, **overrides: Any) -> FitResult:
        """Fit the calibration models to the recorded steps, stored with the campaign unless
        `save=False`; `out` as in `labrunner.fit` (a non-empty directory only with `force`)."""
        if out is not None:  # before reading and fitting: a refused directory costs nothing
            check_output(out, store=self.db.path, force=force, directory=True, option="out")
        return fit(self.data(), options=options, save=save, out=out, force=force, progress=progress, **overrides)

    def diagnose(self, **options: Any) -> Diagnosis:
        """Diagnose the simulated IMU model against this campaign, monitor rows included (see `labrunner.diagnose`)."""
        return diagnose(self.db.path, campaign=self.id, **options)  # the store's bounded-memory path

    def export_csv(self, path: Any, include_monitor: bool = False, force: bool = False) -> int:
        """Write the campaign CSV format (a path or a text stream); returns the number of rows. A path
        may not be the store (or its -wal/-shm), and an existing file is overwritten only with `force`.
        Written block by block from the store (bounded memory), as `labrunner export` does."""
        from labrunner.campaign_csv import export_campaign

        return export_campaign(self._store, self.id, path, include_monitor=include_monitor, force=force)

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
        pending = stp[stp.status != "done"]
        nxt = None
        if not pending.empty:
            row = pending.iloc[0]
            nxt = NextStep(int(row.idx), str(row.orientation), float(row.temperature_c), float(row.rate_dps))
        alive = process_alive(info.pid, info.host, info.lease_wall)
        # A wall-time ETA only for a session that runs: a killed one's pace tells nothing of when it ends.
        live = _live(store, info, self.procedure(), trans, nxt, running=info.status == "running" and alive)
        lab_time, eta, estimated = live.lab_time_s, live.lab_left_s if nxt is not None else None, done == 0
        return CampaignStatus(
            campaign_id=self.id, name=info.name, db=self.db.path, status=info.status,
            process_alive=alive, mode=info.mode, state=state,
            steps_done=done, steps_total=total, samples=int(stp.n_samples.fillna(0).sum()), lab_time_s=lab_time,
            next_step=nxt,
            eta_s=eta, eta_estimated=estimated, updated_wall=info.updated_wall, chamber_c=live.chamber_c,
            imu_temp_c=live.imu_temp_c, soak=live.soak if state == "soaking" else None,
            eta_wall_s=live.eta_wall_s if nxt is not None else None,
            faults=int(trans.kind.isin(["fault", "interlock"]).sum()), rerecorded_steps=int((stp.attempts > 1).sum()),
            recent_events=tuple(Event(float(e.t_s), str(e.kind), None if e.state is None else str(e.state),
                                      None if e.step_idx is None or e.step_idx != e.step_idx else int(e.step_idx),
                                      str(e.message)) for e in recent.itertuples()))

    def __repr__(self) -> str:
        info = self.info
        return f"<labrunner.Campaign {self.id} '{info.name}' {info.status} in {self.db.path}>"


# --- the live view of `labrunner status` ---------------------------------------------------------------


@dataclass(frozen=True)
class _Live:
    lab_time_s: float
    chamber_c: float | None
    imu_temp_c: float | None
    soak: SoakProgress | None
    lab_left_s: float
    eta_wall_s: float | None


def _live(store: Store, info: CampaignInfo, procedure: Procedure, events: pd.DataFrame, nxt: NextStep | None,
          *, running: bool) -> _Live:
    """What the progress bar of the process running the campaign shows, read from the store: the latest
    readings, the soak's progress and the ETA, reckoned as the bar does (`campaign_session.LiveView`)."""
    import numpy as np

    from labrunner.runner.pace import PaceEstimator, Schedule

    latest = _blocks(store, info.id, latest=True)
    block_end = max((b.t[-1] for b in latest), default=0.0)
    # The latest of the heartbeat, the events and the stored samples: a virtual clock stores an hour of
    # soak as monitor means between two events, and the heartbeat is written every 2 s of wall time.
    heartbeat = (info.updated_wall, info.clock_last - info.clock_t0)
    last_event = (float(events.wall.iloc[-1]), float(events.t_s.iloc[-1])) if len(events) else heartbeat
    lab_time = max(heartbeat[1], last_event[1], block_end)
    chamber = imu = None
    if latest:
        chamber, imu = float(latest[0].chamber[-1]), float(latest[0].imu[-1])
        imu = imu if np.isfinite(imu) else None

    schedule = Schedule.of(procedure.estimated_step_ends_s())
    known = None if info.mode == "sim" else float((info.lab_config.get("clock") or {}).get("speed", 1.0))
    pace = PaceEstimator(schedule.total_s, lab_per_wall=known)
    starts = events[(events.kind == "transition") & events.message.str.startswith("idle ->")]
    k = None if nxt is None else nxt.idx
    if running and len(starts):  # this session's pace, from its start, as the running process's bar
        first = starts.iloc[-1]
        step0 = None if first.step_idx != first.step_idx or first.step_idx is None else int(first.step_idx)
        pace.update(float(first.wall), float(first.t_s), schedule.done_s(step0, 0.0))
        since = float(first.t_s)
    else:  # the whole campaign's, for the lab time left only
        pace.update(info.created_wall, 0.0, 0.0)
        since = 0.0
    records = events[(events.kind == "record") & (events.t_s >= since)]
    step_t = float(records.t_s.iloc[-1]) if len(records) else since
    wall_now, lab_now = max(heartbeat, last_event)  # a pair taken at one moment, the later of the two
    eta = pace.update(wall_now, lab_now, schedule.done_s(k, lab_now - step_t))

    soak = None
    if nxt is not None:
        soaks = events[(events.kind == "transition") & (events.state == "soaking")]
        if len(soaks):
            soak = _stored_soak(store, info.id, procedure, float(soaks.t_s.iloc[-1]), nxt.temperature_c, lab_time)
    return _Live(lab_time_s=lab_time, chamber_c=chamber, imu_temp_c=imu, soak=soak, lab_left_s=eta.lab_left_s,
                 eta_wall_s=eta.wall_left_s if running else None)


@dataclass(frozen=True)
class _Readings:
    """One stored sample block's rows: times, IMU temperatures, and the chamber at those times."""

    t: Any  # numpy arrays, (n,)
    imu: Any
    chamber: Any


def _blocks(store: Store, campaign_id: int, *, latest: bool = False, since_t: float = 0.0) -> list[_Readings]:
    """The latest sample block (of either kind), or the monitor blocks from `since_t` on, decoded only as far
    as the live view needs (times, IMU temperature, chamber): one indexed query, no samples frame."""
    import numpy as np
    from sqlalchemy import select

    from labrunner.store import sample_blocks as sb

    q = select(sb.c.t0_s, sb.c.rate_hz, sb.c.n, sb.c.counter, sb.c.encoding, sb.c.temp_lsb, sb.c.temp_c,
               sb.c.chamber).where(sb.c.campaign_id == campaign_id)
    q = q.order_by(sb.c.t0_s.desc()).limit(1) if latest else \
        q.where(sb.c.kind == "monitor", sb.c.t0_s >= since_t).order_by(sb.c.t0_s)
    out = []
    with store.reading() as conn:
        for r in conn.execute(q):
            counter = np.frombuffer(r.counter, dtype="<i4").astype(float)
            pairs = np.frombuffer(r.chamber, dtype="<f8").reshape(-1, 2)
            if not counter.size or not pairs.size:
                continue
            if r.encoding == "i16":
                imu = np.frombuffer(r.temp_c, dtype="<i2") * float(r.temp_lsb)
            else:
                imu = np.frombuffer(r.temp_c, dtype="<f4").astype(float)
            t = r.t0_s + (counter - counter[0]) / r.rate_hz
            out.append(_Readings(t=t, imu=imu, chamber=np.interp(t, pairs[:, 0], pairs[:, 1])))
    return out


def _stored_soak(store: Store, campaign_id: int, procedure: Procedure, soak_t: float, setpoint_c: float,
                 lab_time: float) -> SoakProgress | None:
    """The soak's progress from the monitor means stored since it began (1 s means, where the running
    process judges its polls: the same window, tolerance and rule, `runner.soak.soak_progress`)."""
    from labrunner.runner.soak import SoakReading, soak_progress

    soak = procedure.model.soak
    since = max(soak_t, lab_time - soak.stable_window_s - procedure.model.soak.poll_s)
    readings = [SoakReading(float(t), float(c), float(i)) for b in _blocks(store, campaign_id, since_t=since)
                for t, c, i in zip(b.t, b.chamber, b.imu)]
    return soak_progress(readings, soak, setpoint_c, first_t=soak_t)
