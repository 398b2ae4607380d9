"""The Python API: run campaigns and read what they recorded, as the command line does.

    import labrunner

    result = labrunner.run("procedures/quick.yaml", db="quick.db")       # a dry run on the simulated lab
    with labrunner.open("quick.db") as db:
        campaign = db.campaign()                                         # the latest campaign
        samples = campaign.samples()                                     # pandas, CSV columns + step columns
        fit = campaign.fit()                                             # what `labrunner fit` computes

The pieces live in small modules, gathered here (and re-exported by `labrunner`):
`campaign_session` composes a lab, a store and the runner (run, resume), `campaign_abort` ends a
campaign from outside, `database` reads
a store (`Database`, `Campaign`, `CampaignStatus`), `campaign_analysis` fits and diagnoses.

Every function raises `labrunner.UserError` (with a message naming the file, line or campaign) for
inputs a user can fix. Heavy modules (pandas, the sims, the fitters) are imported when first used,
so `import labrunner` stays fast. See docs/api.md.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labrunner.campaign_abort import AbortResult, abort_campaign
from labrunner.campaign_analysis import diagnose, fit, load_data, read_campaign_csv, write_fit
from labrunner.campaign_session import Progress, ProgressCallback, RunResult, Session, start_resume, start_run
from labrunner.database import Campaign, CampaignStatus, CampaignSummary, Database, Event, NextStep, open_database
from labrunner.errors import UserError
from labrunner.output_paths import OutputPathError, check_output

if TYPE_CHECKING:
    from labrunner.lab import LabConfig
    from labrunner.procedure import Procedure
    from labrunner.report_html import ReportResult
    from labrunner.sims.lab import SimLab
    from labrunner.sims.world import SimLabConfig

log = logging.getLogger(__name__)

__all__ = [
    "AbortResult", "Campaign", "CampaignStatus", "CampaignSummary", "Database", "Event", "NextStep", "OutputPathError",
    "Progress", "RunResult", "Session", "UserError", "abort", "check_output", "diagnose", "fit", "list_campaigns",
    "load_data", "load_lab_config", "load_procedure", "load_sim_config", "open", "read_campaign_csv", "report",
    "resume", "run", "serve_sim", "start_resume", "start_run", "status", "write_fit",
]


# --- running -------------------------------------------------------------------------------------------------


def run(procedure: str | Path | Procedure, *, db: str | Path, lab: str | Path | LabConfig = "sim",
        seed: int | None = None, faults: int = 0, sim_config: str | Path | dict[str, Any] | None = None,
        fit_out: str | Path | None = None, auto_resume: bool = True, progress: ProgressCallback | None = None,
        handle_signals: bool = False, force: bool = False) -> RunResult:
    """Run `procedure` (a YAML path or a parsed `Procedure`) as a new campaign stored in `db`.

    `lab="sim"` is a dry run against the simulated lab on a virtual clock (`seed`, `faults` random
    injected faults, `sim_config` a path or mapping); otherwise `lab` is a lab configuration (YAML
    path or `LabConfig`). The end-of-run fit (the procedure's `fit:`) writes its models to `fit_out`
    (default `<db>_fit/campaign-<id>/` next to the database; one that is not empty only with `force`,
    checked before the run starts). `progress` is called with a `Progress` after every
    transition and record. `handle_signals`: Ctrl-C pauses, a second one aborts to the safe state.
    """
    with start_run(procedure, db=db, lab=lab, seed=seed, faults=faults, sim_config=sim_config, fit_out=fit_out,
                   auto_resume=auto_resume, force=force) as session:
        return session.execute(progress, handle_signals=handle_signals)


def resume(db: str | Path, *, campaign: int | None = None, lab: str | Path | LabConfig | None = None,
           fit_out: str | Path | None = None, progress: ProgressCallback | None = None,
           handle_signals: bool = False, force: bool = False) -> RunResult:
    """Continue a paused, aborted, failed or killed campaign (default: the latest in `db`) from its
    first missing step; a real lab uses the stored lab configuration unless `lab` is given. A given
    `fit_out` must be empty or new unless `force`."""
    with start_resume(db, campaign=campaign, lab=lab, fit_out=fit_out, force=force) as session:
        return session.execute(progress, handle_signals=handle_signals)


def abort(db: str | Path, *, campaign: int | None = None, wait_s: float = 60.0,
          notify: Callable[[str], None] | None = None) -> AbortResult:
    """Bring a campaign's lab to its safe state (table stopped, chamber to the remount temperature)
    and end the run; it stays resumable. A running process is asked to stop and given `wait_s`;
    with none running, a real lab is made safe from here. `notify` gets progress messages
    (default: logged as warnings)."""
    return abort_campaign(db, campaign=campaign, wait_s=wait_s, notify=notify or log.warning)


# --- reading ------------------------------------------------------------------------------------------------


def open(db: str | Path) -> Database:  # noqa: A001 - `labrunner.open(db)`, as `sqlite3.connect`/`h5py.File`
    """Open a labrunner store for reading (a context manager; also usable while a campaign runs)."""
    return open_database(db)


def list_campaigns(db: str | Path) -> list[CampaignSummary]:
    """Every campaign in `db` (what `labrunner list` shows): id, name, status, steps recorded/planned,
    samples, mode, the process holding a running one and the age of its last heartbeat."""
    with open(db) as database:
        return database.summaries()


def status(db: str | Path, *, campaign: int | None = None, events: int = 8) -> CampaignStatus:
    """The progress of a campaign (default: the latest in `db`) and its `events` most recent events."""
    with open(db) as database:
        return database.campaign(campaign).status_report(events=events)


def report(db: str | Path, *, html: str | Path, campaign: int | None = None, force: bool = False) -> ReportResult:
    """Write a campaign's report (default: the latest in `db`) as one self-contained HTML file
    (`labrunner report`): headline, overview plot, steps and events, the stored fit's figures and
    tables, provenance. `html` may not be the store; an existing file only with `force`."""
    from labrunner.report_html import write_report

    return write_report(db, html, campaign=campaign, force=force)


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
    _check_serving(host, profile, ports)
    sim_config = load_sim_config(config)
    try:
        lab = SimLab(sim_config, ScaledClock(speed), host=host, link=link, chamber_transport=chamber_transport,
                     chamber_profile=profile, ports=SimPorts(chamber=ports[0], table=ports[1], imu=ports[2]))
    except (OSError, ValueError) as exc:  # ValueError: a profile that cannot show the configured units
        raise UserError(f"cannot start the simulated lab: {exc}") from None
    log.info("simulated lab serving on %s at %gx", host, speed)
    return lab


def _check_serving(host: str, profile: str, ports: tuple[int, int, int]) -> None:
    """What the servers would fail on deep inside (a ValueError from the profile table, pymodbus' "could not
    start listen", an OverflowError from bind), said first and naming the argument."""
    import socket

    from labrunner.drivers.chamber_profiles import profile_from

    try:
        profile_from(profile)
    except ValueError as exc:
        raise UserError(f"--profile: {exc}") from None
    bad = [p for p in ports if not 0 <= p <= 65535]
    if bad:
        raise UserError(f"port {bad[0]} out of range: ports are 0 (any free one) to 65535")
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.bind(address)
    except OSError as exc:
        raise UserError(f"--host {host}: cannot listen there ({exc.strerror or exc})") from None
