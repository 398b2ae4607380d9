"""`labrunner run | resume | status | abort | export`: campaigns from a terminal.

Argument parsing and printing only; the campaign is composed, run and read by `labrunner.api`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from labrunner.commands.progress import ProgressBar, clock_text
from labrunner.commands.types import count, interval, seconds
from labrunner.store_address import StoreAddress, store_arg

if TYPE_CHECKING:  # the handlers import it: building the parser must not load the sequencer, store and sims
    from labrunner import api


def register(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser(
        "run", help="run a procedure (on the lab, or --sim for a dry run)",
        description="Run a procedure as a new campaign: ramp and soak the chamber, spin the table, record the "
                    "IMU, step by step, storing every sample and event in the database; fit the calibration "
                    "models at the end. A progress bar and an ETA go to stderr, the fit's summary to stdout.\n\n"
                    "Ctrl-C pauses at the next safe point; a second Ctrl-C, SIGTERM or `labrunner abort DB` "
                    "brings the lab to its safe state. Either way `labrunner resume DB` continues.\n\n"
                    "Exit codes: 0 done, 3 paused, 4 aborted (lab in safe state), 1 failed, 2 bad input.",
        epilog="""\
examples:
  labrunner run quick --sim --db quick.db                   # dry run of the shipped quick procedure
  labrunner run quick --sim --faults 5 --db night.db        # rehearse a bad night: 5 injected faults
  labrunner run procedures/paper_campaign.yaml --lab lab.yaml --db c1.db   # on the real instruments""")
    run.add_argument("procedure", type=Path, metavar="PROCEDURE",
                     help="procedure YAML, or the name of a shipped one (quick, paper_campaign)")
    run.add_argument("--db", type=store_arg, required=True, metavar="DB",
                     help="SQLite database for the campaign (created if new; may hold other campaigns)")
    where = run.add_mutually_exclusive_group(required=True)
    where.add_argument("--sim", action="store_true", help="dry run against the simulated lab (virtual clock)")
    where.add_argument("--lab", type=Path, metavar="LAB.yaml", help="lab configuration naming the instruments")
    run.add_argument("--sim-config", type=Path, metavar="SIM.yaml",
                     help="dry runs: sim configuration (seed, plants, IMU model, faults)")
    run.add_argument("--seed", type=count, default=None, metavar="N",
                     help="dry runs: seed of the simulated lab (default: the sim configuration's)")
    run.add_argument("--faults", type=count, default=0, metavar="N",
                     help="dry runs: inject N seeded random instrument faults across the campaign")
    run.add_argument("--fit-out", type=Path, default=None, metavar="DIR",
                     help="directory for the fitted models (default: next to the database, <db>_fit/campaign-<id>/)")
    run.add_argument("--force", action="store_true", help="let the end-of-run fit write into a non-empty --fit-out")
    run.add_argument("--no-auto-resume", action="store_true",
                     help="dry runs with injected faults: stop at a fault pause instead of resuming after 15 min "
                          "of lab time as an operator would")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.set_defaults(func=cmd_run)

    res = sub.add_parser(
        "resume", help="continue a paused, killed or aborted campaign from its first missing step",
        description="Continue a campaign that was paused, aborted, or killed (kill -9, power loss) from its first "
                    "missing step, with the procedure and configuration stored in the database. Complete steps "
                    "are never recorded again. Exit codes as for `run`.",
        epilog="""\
examples:
  labrunner resume quick.db
  labrunner resume c1.db --campaign 2 --lab lab.yaml        # the second campaign, on another lab set-up""")
    res.add_argument("db", type=store_arg, metavar="DB", help="the campaign's database")
    res.add_argument("--campaign", type=int, default=None, metavar="N",
                     help="campaign id (default: the latest in the database)")
    res.add_argument("--lab", type=Path, metavar="LAB.yaml", help="lab configuration (default: the one stored)")
    res.add_argument("--fit-out", type=Path, default=None, metavar="DIR",
                     help="directory for the fitted models (default: next to the database, <db>_fit/campaign-<id>/)")
    res.add_argument("--force", action="store_true", help="let the end-of-run fit write into a non-empty --fit-out")
    res.add_argument("--take-over", action="store_true",
                     help="take the campaign's lease from a holder whose last heartbeat is more than 60 s old "
                          "(make sure that process is stopped first); a live holder is always refused")
    res.add_argument("--quiet", action="store_true", help="no progress bar")
    res.set_defaults(func=cmd_resume)

    st = sub.add_parser(
        "status", help="progress of a campaign (also while it runs in another terminal)",
        description="Show a campaign's status, state, progress, lab time, the latest chamber and IMU "
                    "temperatures, a soak's progress (spread over the window against the tolerance, time stable), "
                    "next step, ETA (lab time left, and wall time at the measured pace), faults and recent events. "
                    "Safe while the campaign runs in another process.",
        epilog="""\
examples:
  labrunner status quick.db
  labrunner status quick.db --watch 5 --events 15           # refresh every 5 s until the campaign ends""")
    st.add_argument("db", type=store_arg, metavar="DB", help="the campaign's database")
    st.add_argument("--campaign", type=int, default=None, metavar="N",
                    help="campaign id (default: the latest in the database)")
    st.add_argument("--events", type=count, default=8, metavar="N", help="how many recent events to show")
    st.add_argument("--watch", type=interval, default=None, metavar="S",
                    help="refresh every S seconds until the campaign ends (done, paused, aborted, failed, or its "
                         "process gone; exit 0 with its final state) or Ctrl-C (default: print once)")
    st.set_defaults(func=cmd_status)

    ab = sub.add_parser(
        "abort", help="bring the lab to its safe state and end a campaign",
        description="Abort a campaign: the process running it (found through the database) stops the table and "
                    "takes the chamber to the remount temperature, its safe state; when no process runs it, this "
                    "command does that itself on a real lab. The campaign stays resumable with `labrunner resume "
                    "DB`. Exit code 0 when it ended safely (or already had), 1 when the running process did not "
                    "answer within --wait.",
        epilog="""\
examples:
  labrunner abort quick.db
  labrunner abort c1.db --campaign 2 --wait 300""")
    ab.add_argument("db", type=store_arg, metavar="DB", help="the campaign's database")
    ab.add_argument("--campaign", type=int, default=None, metavar="N",
                    help="campaign id (default: the latest in the database)")
    ab.add_argument("--wait", type=seconds, default=60.0, metavar="S",
                    help="seconds to wait for the running process to reach the safe state")
    ab.set_defaults(func=cmd_abort)

    ex = sub.add_parser(
        "export", help="write a campaign as campaign CSV",
        description="Write a campaign's recorded samples in the campaign CSV format (t_s, run, orientation, "
                    "chamber_c, imu_temp_c, table_rate_dps, ax_g ... gz_dps), the input of `fit`, `diagnose` "
                    "and `check --csv`.",
        epilog="""\
examples:
  labrunner export quick.db --csv quick.csv
  labrunner export quick.db --csv - --with-monitor | head   # to stdout, with the ramp and soak rows""")
    ex.add_argument("db", type=store_arg, metavar="DB", help="the campaign's database")
    ex.add_argument("--csv", type=Path, required=True, metavar="FILE", help="output CSV file ('-' for stdout)")
    ex.add_argument("--campaign", type=int, default=None, metavar="N",
                    help="campaign id (default: the latest in the database)")
    ex.add_argument("--force", action="store_true", help="overwrite an existing CSV file")
    ex.add_argument("--with-monitor", action="store_true",
                    help="include the 1 s monitor rows logged while ramping and soaking")
    ex.set_defaults(func=cmd_export)


# --- run, resume ---------------------------------------------------------------------------------------


def rerecorded_text(campaign_wide: int, session: int) -> str:
    """Steps recorded more than once, in `status`'s words; this session's share when it differs."""
    return f"re-recorded steps: {campaign_wide}" + (f" ({session} this session)" if session != campaign_wide else "")


def _execute(session: api.Session, quiet: bool, db: StoreAddress) -> int:
    bar = ProgressBar(session.steps_total, quiet, initial=session.steps_done)  # a resumed one: where it was
    try:
        r = session.execute(None if quiet else bar, handle_signals=True)
    finally:
        bar.close()
    print(f"campaign {r.campaign_id} in {db}: {r.state}. {r.steps_done}/{r.steps_total} steps recorded "
          f"({r.steps_recorded} this session, {r.samples} samples, {r.faults} faults); "
          f"{rerecorded_text(r.steps_rerecorded, r.steps_rerecorded_session)}; "
          f"lab time {r.lab_time_s / 3600:.2f} h, wall {r.wall_s:.1f} s", file=sys.stderr)
    if r.faults_injected is not None:
        kinds = ", ".join(f"{k} {v}" for k, v in sorted(r.faults_by_kind.items()))
        print(f"faults injected: {r.faults_injected} ({kinds}); auto-resumed {r.auto_resumes} time(s), "
              f"{r.recoveries} recoveries logged", file=sys.stderr)
    if r.reason:
        print(f"reason: {r.reason}", file=sys.stderr)
    if r.resumable:
        print(f"continue with: labrunner resume {db}", file=sys.stderr)
    if r.fit_summary:
        print(r.fit_summary)
        if r.fit_out is not None:
            print(f"\nmodels written to {r.fit_out}/", file=sys.stderr)
    return r.exit_code


def cmd_run(args: argparse.Namespace) -> int:
    from labrunner import api

    with api.start_run(args.procedure, db=args.db, lab="sim" if args.sim else args.lab, seed=args.seed,
                       faults=args.faults, sim_config=args.sim_config, fit_out=args.fit_out,
                       auto_resume=not args.no_auto_resume, force=args.force) as session:
        _tell(f"campaign {session.campaign_id} '{session.procedure.name}' in {args.db}: {session.steps_total} steps, "
              f"{session.planned_samples:,} samples planned, about {session.estimated_lab_s / 3600:.1f} h of lab "
              "time" + (" (dry run, simulated lab)" if args.sim else ""))
        return _execute(session, args.quiet, args.db)


def cmd_resume(args: argparse.Namespace) -> int:
    from labrunner import api

    with api.start_resume(args.db, campaign=args.campaign, lab=args.lab, fit_out=args.fit_out,
                          force=args.force, take_over=args.take_over) as session:
        if session.lease_note:
            _tell(session.lease_note)
        if session.already_done:
            print(f"campaign {session.campaign_id} in {args.db} is complete; nothing to resume")
            return 0
        _tell(f"resuming campaign {session.campaign_id} '{session.procedure.name}' ({session.status_before}) at "
              f"step {session.next_step} of {session.steps_total}")
        return _execute(session, args.quiet, args.db)


def _tell(line: str) -> None:
    """A line on stderr before the campaign starts. A closed stderr (`2>&1 | head` gone) must not leave a
    campaign created and never run: the line is lost, the campaign runs (the progress bar goes quiet too)."""
    try:
        print(line, file=sys.stderr)
    except OSError:
        pass


# --- status ------------------------------------------------------------------------------------------


def status_text(s: api.CampaignStatus) -> str:
    status = s.status + (" (process gone: resume it)" if s.status == "running" and not s.process_alive else "")
    lines = [f"campaign {s.campaign_id} '{s.name}' in {s.db}", f"  status      {status}",
             f"  mode        {'dry run (simulated lab)' if s.mode == 'sim' else 'lab'}",
             f"  state       {s.state}",
             f"  progress    {s.steps_done}/{s.steps_total} steps ({100.0 * s.fraction_done:.1f} %), "
             f"{s.samples:,} samples",
             f"  lab time    {s.lab_time_s / 3600:.2f} h"]
    if s.chamber_c is not None or s.imu_temp_c is not None:
        lines.append(f"  measured    chamber {_celsius(s.chamber_c)}, IMU {_celsius(s.imu_temp_c)} (latest stored)")
    if s.soak is not None:
        k = s.soak
        spread = (f"IMU spread {k.imu_spread_c:.2f} C of {k.tolerance_c:g} C allowed" if k.sensor == "imu" else
                  f"chamber off by {k.chamber_offset_c:.2f} C of {k.tolerance_c:g} C allowed")
        lines.append(f"  soak        at {k.setpoint_c:+g} C: {spread} over the last {k.window_s:.0f} s; stable "
                     f"{k.stable_s:.0f} of {k.window_s:.0f} s (soaking {k.soaked_s / 60:.0f} min)")
    if s.next_step is not None:
        n = s.next_step
        lines.append(f"  next step   {n.idx}: {n.orientation} {n.temperature_c:+g} C {n.rate_dps:+g} deg/s")
        if s.eta_s is not None:
            how = "the procedure's estimate" if s.eta_estimated else "the plan, corrected by the pace so far"
            wall = f", {clock_text(s.eta_wall_s)} of wall time at the measured pace" if s.eta_wall_s is not None \
                else ""
            lines.append(f"  ETA         about {s.eta_s / 3600:.1f} h of lab time left ({how}){wall}")
    lines.append(f"  updated     {time.time() - s.updated_wall:.0f} s ago")
    lines.append(f"  faults      {s.faults}   re-recorded steps: {s.rerecorded_steps}")
    lines.append("  recent events:")
    for e in s.recent_events:
        lines.append(f"    {e.t_s / 3600:8.3f} h  {e.kind:10s} {e.message}")
    return "\n".join(lines)


def _celsius(value: float | None) -> str:
    return "?" if value is None else f"{value:.2f} C"


def cmd_status(args: argparse.Namespace) -> int:
    from labrunner import api

    s = api.status(args.db, campaign=args.campaign, events=args.events)
    if not args.watch:
        print(status_text(s))
        return 0
    try:
        while True:
            print("\033[2J\033[H" + status_text(s), flush=True)
            if s.over:  # done, paused, aborted, failed, or its process gone: nothing more will change
                print(f"campaign {s.campaign_id} ended: {s.status}"
                      + (" (process gone: resume it)" if s.status == "running" else ""), flush=True)
                return 0
            time.sleep(args.watch)
            s = api.status(args.db, campaign=s.campaign_id, events=args.events)  # the one it began with
    except KeyboardInterrupt:
        return 0


# --- abort, export -------------------------------------------------------------------------------------


def cmd_abort(args: argparse.Namespace) -> int:
    from labrunner import api

    r = api.abort(args.db, campaign=args.campaign, wait_s=args.wait,
                  notify=lambda msg: print(msg, file=sys.stderr, flush=True))
    if r.outcome == "already":
        print(f"campaign {r.campaign_id} is already {r.status}")
    elif r.outcome == "requested":
        print(f"campaign {r.campaign_id}: {r.status}")
    else:
        print(f"campaign {r.campaign_id}: aborted (resumable with labrunner resume {args.db})")
    return 0 if r.ok else 1


def cmd_export(args: argparse.Namespace) -> int:
    from labrunner import api
    from labrunner.campaign_csv import export_campaign

    with api.open(args.db) as db:
        campaign = db.campaign(args.campaign)
        to_stdout = str(args.csv) == "-"
        # Block by block from the store (bounded memory), as `Campaign.export_csv` writes the same file.
        rows = export_campaign(db.store, campaign.id, sys.stdout if to_stdout else args.csv,
                               include_monitor=args.with_monitor, force=args.force)
    if not to_stdout:
        print(f"wrote {rows:,} rows of campaign {campaign.id} to {args.csv}", file=sys.stderr)
    return 0
