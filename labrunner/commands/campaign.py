"""`labrunner run | resume | status | abort | export`: campaigns from a terminal."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from labrunner.errors import UserError

EXIT = {"done": 0, "paused": 3, "aborted": 4, "failed": 1}
AUTO_RESUME_S = 900.0  # a rehearsed operator resumes a fault pause after 15 minutes (lab time)


def register(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser("run", help="run a procedure (on the lab, or --sim for a dry run)",
                         description="Run a YAML procedure as a new campaign stored in --db.")
    run.add_argument("procedure", type=Path, help="procedure YAML (e.g. procedures/quick.yaml)")
    run.add_argument("--db", type=Path, required=True, help="SQLite database for the campaign (created if new)")
    where = run.add_mutually_exclusive_group(required=True)
    where.add_argument("--sim", action="store_true", help="dry run against the simulated lab (virtual clock)")
    where.add_argument("--lab", type=Path, metavar="LAB.yaml", help="lab configuration naming the instruments")
    run.add_argument("--sim-config", type=Path, help="sim configuration YAML (seed, plants, IMU model, faults)")
    run.add_argument("--seed", type=int, default=None, help="seed of the simulated lab (dry runs)")
    run.add_argument("--faults", type=int, default=0, metavar="N",
                     help="dry runs: inject N seeded random instrument faults across the campaign")
    run.add_argument("--fit-out", type=Path, default=None,
                     help="directory for the fitted models (default: next to the database, <db>_fit/)")
    run.add_argument("--no-auto-resume", action="store_true",
                     help="dry runs with injected faults: stop at a fault pause instead of resuming after 15 min "
                          "of lab time as an operator would")
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    run.set_defaults(func=cmd_run)

    res = sub.add_parser("resume", help="continue a paused, killed or aborted campaign from its first missing step")
    res.add_argument("db", type=Path)
    res.add_argument("--campaign", type=int, default=None, help="campaign id (default: the latest in the file)")
    res.add_argument("--lab", type=Path, metavar="LAB.yaml", help="lab configuration (default: the one stored)")
    res.add_argument("--fit-out", type=Path, default=None)
    res.add_argument("--quiet", action="store_true")
    res.set_defaults(func=cmd_resume)

    st = sub.add_parser("status", help="progress of a campaign (also while it runs in another terminal)")
    st.add_argument("db", type=Path)
    st.add_argument("--campaign", type=int, default=None)
    st.add_argument("--events", type=int, default=8, help="how many recent events to show")
    st.add_argument("--watch", type=float, default=None, metavar="S", help="refresh every S seconds")
    st.set_defaults(func=cmd_status)

    ab = sub.add_parser("abort", help="bring the lab to its safe state and end a campaign")
    ab.add_argument("db", type=Path)
    ab.add_argument("--campaign", type=int, default=None)
    ab.add_argument("--wait", type=float, default=60.0, help="seconds to wait for the running process")
    ab.set_defaults(func=cmd_abort)

    ex = sub.add_parser("export", help="write a campaign as campaign CSV")
    ex.add_argument("db", type=Path)
    ex.add_argument("--csv", type=Path, required=True, help="output CSV file ('-' for stdout)")
    ex.add_argument("--campaign", type=int, default=None)
    ex.add_argument("--with-monitor", action="store_true",
                    help="include the 1 s monitor rows logged while ramping and soaking")
    ex.set_defaults(func=cmd_export)


# --- helpers -------------------------------------------------------------------------------------


def _crash_hook() -> Any:
    """LABRUNNER_CRASH_AT=point:N kills this process (SIGKILL) the N-th time it reaches point (tests)."""
    spec = os.environ.get("LABRUNNER_CRASH_AT")
    if not spec:
        return None
    point, _, nth = spec.partition(":")
    target = int(nth or 1)
    seen = {"n": 0}

    def hook(where: str) -> None:
        if where == point:
            seen["n"] += 1
            if seen["n"] == target:
                os.kill(os.getpid(), signal.SIGKILL)

    return hook


class _ProgressBar:
    def __init__(self, total: int, quiet: bool) -> None:
        self.bar = None
        if not quiet:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="step", file=sys.stderr, dynamic_ncols=True, mininterval=0.5,
                            smoothing=0.05, bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} steps "
                                                       "[{elapsed}<{remaining}] {postfix}")

    def __call__(self, runner: Any) -> None:
        if self.bar is None:
            return
        done = runner.done_steps()
        if done > self.bar.n:
            self.bar.update(done - self.bar.n)
        step = runner.current_step()
        where = f"{step.orientation} {step.temperature_c:+g}C {step.rate_dps:+g}dps" if step else ""
        self.bar.set_postfix_str(f"{runner.state:13s} {where} lab time {runner.t / 3600:6.2f} h", refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _install_signals(runner: Any) -> None:
    hits = {"n": 0}

    def on_sigint(_sig: int, _frame: Any) -> None:
        hits["n"] += 1
        if hits["n"] == 1:
            print("\nlabrunner: pausing at the next safe point (Ctrl-C again to abort to a safe state)",
                  file=sys.stderr, flush=True)
            runner.request_pause("Ctrl-C: pause")
        else:
            print("\nlabrunner: aborting: bringing the lab to its safe state", file=sys.stderr, flush=True)
            runner.request_abort("Ctrl-C twice: abort")

    signal.signal(signal.SIGINT, on_sigint)
    signal.signal(signal.SIGTERM, lambda *_: runner.request_abort("SIGTERM: abort"))


def _fit_dir(db: Path, given: Path | None) -> Path:
    return given if given is not None else db.with_name(db.stem + "_fit")


def _execute(runner: Any, quiet: bool, db: Path) -> int:
    bar = _ProgressBar(len(runner.plan), quiet)
    runner.progress = bar
    _install_signals(runner)
    try:
        final = runner.run()
    finally:
        bar.close()
        runner.lab.close()
    s = runner.stats
    print(f"campaign {runner.cid} in {db}: {final}. {runner.done_steps()}/{len(runner.plan)} steps recorded "
          f"({s.steps_recorded} this session, {s.samples} samples, {s.steps_rerecorded} recorded again, "
          f"{s.faults} faults); lab time {runner.t / 3600:.2f} h, wall {time.time() - s.started_wall:.1f} s",
          file=sys.stderr)
    inj = getattr(runner, "fault_injector", None)
    if inj is not None:
        print(f"faults injected: {inj.injected} ({', '.join(f'{k} {v}' for k, v in sorted(inj.by_kind.items()))}); "
              f"auto-resumed {runner.auto_resumes} time(s), {s.recoveries} recoveries logged", file=sys.stderr)
    if runner.last_error and final != "done":
        print(f"reason: {runner.last_error}", file=sys.stderr)
    if final in ("paused", "aborted", "failed"):
        print(f"continue with: labrunner resume {db}", file=sys.stderr)
    if runner.fit_summary:
        print(runner.fit_summary)
        if runner.fit_ok and runner.fit_out_dir:
            print(f"\nmodels written to {runner.fit_out_dir}/", file=sys.stderr)
    return EXIT[final]


def _sim_lab(procedure: Any, sim_dict: dict[str, Any], start_t: float, orientation: str | None) -> Any:
    from labrunner.lab import simulated_lab
    from labrunner.sims.world import SimLabConfig

    try:
        config = SimLabConfig.from_dict(sim_dict)
    except (ValueError, TypeError, OSError) as exc:
        raise UserError(f"sim configuration: {exc}") from None
    return simulated_lab(max_rate_dps=procedure.model.safety.max_rate_dps, sim_config=config, start_t=start_t,
                         orientation=orientation)


# --- run ---------------------------------------------------------------------------------------------


def cmd_run(args: argparse.Namespace) -> int:
    from labrunner.lab import lab_config_from_dict, load_lab_config, real_lab
    from labrunner.procedure import load_procedure
    from labrunner.sequencer import CampaignRunner
    from labrunner.store import Store

    procedure = load_procedure(args.procedure)
    sim_dict: dict[str, Any] | None = None
    if args.sim:
        from labrunner.commands.sim import sim_config_dict

        sim_dict = sim_config_dict(args.sim_config)
        if args.seed is not None:
            sim_dict["seed"] = args.seed
        if args.faults:
            from labrunner.fault_plan import random_fault_plan

            sim_dict["faults"] = {"random": random_fault_plan(procedure, args.faults, sim_dict.get("seed", 0))}
        first = procedure.steps()[0].orientation
        lab = _sim_lab(procedure, sim_dict, 0.0, first)
        lab_dict = lab.config.model_dump()
    else:
        if args.faults:
            raise UserError("--faults injects faults into the simulated lab: use it with --sim")
        config, _ = load_lab_config(args.lab)
        lab_dict = config.model_dump()
        lab = real_lab(lab_config_from_dict(lab_dict), max_rate_dps=procedure.model.safety.max_rate_dps)
    try:
        store = Store.create(args.db)
    except Exception:
        lab.close()
        raise
    cid = store.new_campaign(name=procedure.name, procedure_text=procedure.text,
                             procedure_path=str(args.procedure.resolve()), procedure_sha256=procedure.sha256,
                             lab_config=lab_dict, mode="sim" if args.sim else "lab", sim_config=sim_dict,
                             clock_t0=lab.clock.now(), plan=procedure.steps())
    auto = AUTO_RESUME_S if (args.sim and _has_fault_plan(sim_dict) and not args.no_auto_resume) else None
    runner = CampaignRunner(procedure, lab, store, cid, fit_out_dir=_fit_dir(args.db, args.fit_out),
                            crash_hook=_crash_hook(), auto_resume_s=auto)
    _attach_faults(runner, lab, sim_dict)
    print(f"campaign {cid} '{procedure.name}' in {args.db}: {len(runner.plan)} steps, "
          f"{len(runner.plan) * procedure.frames_per_record:,} samples planned, about "
          f"{procedure.estimated_duration_s() / 3600:.1f} h of lab time" + (" (dry run, simulated lab)" if args.sim else ""),
          file=sys.stderr)
    try:
        return _execute(runner, args.quiet, args.db)
    finally:
        store.close()


def _has_fault_plan(sim_dict: dict[str, Any] | None) -> bool:
    faults = (sim_dict or {}).get("faults") or {}
    return bool(faults.get("random") or faults.get("schedule"))


def _attach_faults(runner: Any, lab: Any, sim_dict: dict[str, Any] | None) -> None:
    if lab.sim is None or not _has_fault_plan(sim_dict):
        return  # static plant faults (faults.chamber) are applied by the simulated lab itself
    from labrunner.fault_plan import FaultInjector

    FaultInjector.attach(runner, lab, sim_dict["faults"])


# --- resume --------------------------------------------------------------------------------------------


def _alive(pid: int | None, host: str | None) -> bool:
    if not pid or host != os.uname().nodename:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def cmd_resume(args: argparse.Namespace) -> int:
    from labrunner.lab import lab_config_from_dict, load_lab_config, real_lab
    from labrunner.procedure import parse_procedure
    from labrunner.sequencer import CampaignRunner
    from labrunner.store import Store

    store = Store.open_existing(args.db)
    try:
        cid = store.resolve(args.campaign)
        info = store.campaign(cid)
        if info.status == "done":
            print(f"campaign {cid} in {args.db} is complete; nothing to resume")
            return 0
        if info.status == "running" and _alive(info.pid, info.host):
            raise UserError(f"campaign {cid} is running (process {info.pid}); use labrunner status or abort")
        procedure = parse_procedure(info.procedure_text, f"{args.db} (campaign {cid} procedure)")
        nxt = store.next_step(cid)
        orientation = procedure.steps()[nxt].orientation if nxt is not None else None
        if info.mode == "sim":
            # The simulated lab starts again a minute after the campaign's last recorded moment
            # (after a kill the heartbeat's clock_last may lag behind the last event).
            last = max(info.clock_last, info.clock_t0 + store.last_time(cid))
            lab = _sim_lab(procedure, info.sim_config or {}, last + 60.0, orientation)
        else:
            config = load_lab_config(args.lab)[0] if args.lab else lab_config_from_dict(info.lab_config, "stored lab configuration")
            lab = real_lab(config, max_rate_dps=procedure.model.safety.max_rate_dps)
        faulty = info.mode == "sim" and _has_fault_plan(info.sim_config)
        runner = CampaignRunner(procedure, lab, store, cid, fit_out_dir=_fit_dir(args.db, args.fit_out),
                                crash_hook=_crash_hook(), auto_resume_s=AUTO_RESUME_S if faulty else None)
        _attach_faults(runner, lab, info.sim_config)
        print(f"resuming campaign {cid} '{info.name}' ({info.status}) at step {nxt} of {len(runner.plan)}",
              file=sys.stderr)
        return _execute(runner, args.quiet, args.db)
    finally:
        store.close()


# --- status ------------------------------------------------------------------------------------------


def status_text(db: Path, campaign: int | None, n_events: int) -> str:
    from labrunner.procedure import parse_procedure
    from labrunner.store import Store

    with Store.open_existing(db) as store:
        cid = store.resolve(campaign)
        info = store.campaign(cid)
        stp = store.steps_frame(cid)
        ev = store.events_frame(cid, last=n_events)
        trans = store.events_frame(cid)
    done = int((stp.status == "done").sum())
    total = len(stp)
    alive = _alive(info.pid, info.host)
    status = info.status + (" (process gone: resume it)" if info.status == "running" and not alive else "")
    last_state = trans[trans.kind == "transition"].state.iloc[-1] if (trans.kind == "transition").any() else "idle"
    lines = [f"campaign {cid} '{info.name}' in {db}", f"  status      {status}",
             f"  mode        {'dry run (simulated lab)' if info.mode == 'sim' else 'lab'}",
             f"  state       {last_state}",
             f"  progress    {done}/{total} steps ({100.0 * done / max(total, 1):.1f} %), "
             f"{int(stp.n_samples.fillna(0).sum()):,} samples"]
    t_now = info.clock_last - info.clock_t0
    lines.append(f"  lab time    {t_now / 3600:.2f} h")
    pending = stp[stp.status != "done"]
    if not pending.empty:
        nxt = pending.iloc[0]
        lines.append(f"  next step   {int(nxt.idx)}: {nxt.orientation} {nxt.temperature_c:+g} C {nxt.rate_dps:+g} deg/s")
        procedure = parse_procedure(info.procedure_text, "stored procedure")
        if done:
            per_step = t_now / done
            lines.append(f"  ETA         about {per_step * (total - done) / 3600:.1f} h of lab time left "
                         f"(at the pace so far)")
        else:
            lines.append(f"  ETA         about {procedure.estimated_duration_s() / 3600:.1f} h of lab time (estimate)")
    lines.append(f"  updated     {time.time() - info.updated_wall:.0f} s ago")
    n_faults = int((trans.kind.isin(["fault", "interlock"])).sum())
    lines.append(f"  faults      {n_faults}   re-recorded steps: {int((stp.attempts > 1).sum())}")
    lines.append("  recent events:")
    for _, e in ev.iterrows():
        lines.append(f"    {e.t_s / 3600:8.3f} h  {e.kind:10s} {e.message}")
    return "\n".join(lines)


def cmd_status(args: argparse.Namespace) -> int:
    if args.watch:
        try:
            while True:
                text = status_text(args.db, args.campaign, args.events)
                print("\033[2J\033[H" + text, flush=True)
                time.sleep(args.watch)
        except KeyboardInterrupt:
            return 0
    print(status_text(args.db, args.campaign, args.events))
    return 0


# --- abort -------------------------------------------------------------------------------------------


def cmd_abort(args: argparse.Namespace) -> int:
    from labrunner.store import Store

    with Store.open_existing(args.db) as store:
        cid = store.resolve(args.campaign)
        info = store.campaign(cid)
        if info.status in ("done", "aborted"):
            print(f"campaign {cid} is already {info.status}")
            return 0
        if info.status == "running" and _alive(info.pid, info.host):
            store.request(cid, "abort")
            print(f"abort requested; waiting for process {info.pid} to bring the lab to its safe state...",
                  file=sys.stderr)
            deadline = time.time() + args.wait
            while time.time() < deadline:
                time.sleep(0.2)
                if store.campaign(cid).status != "running":
                    break
            final = store.campaign(cid).status
            print(f"campaign {cid}: {final}")
            return 0 if final in ("aborted", "failed", "paused") else 1
        # Nobody is running it: make the lab safe ourselves (a real lab), then mark it aborted.
        if info.mode == "lab":
            _safe_state_directly(info)
        store.event(cid, info.clock_last - info.clock_t0, "operator", "aborted by labrunner abort (no process running)")
        store.set_status(cid, "aborted", pid=None)
        print(f"campaign {cid}: aborted (resumable with labrunner resume {args.db})")
        return 0


def _safe_state_directly(info: Any) -> None:
    from labrunner.lab import lab_config_from_dict, real_lab
    from labrunner.procedure import parse_procedure
    from labrunner.runner.safe_stop import safe_stop

    procedure = parse_procedure(info.procedure_text, "stored procedure")
    lab = real_lab(lab_config_from_dict(info.lab_config, "stored lab configuration"),
                   max_rate_dps=procedure.model.safety.max_rate_dps)
    try:
        result = safe_stop(lab.table, lab.chamber, procedure.model.remount_c, lab.clock, connect=True,
                           on_retry=lambda problems: print("safe state not reached yet, trying again: "
                                                           + "; ".join(problems), file=sys.stderr))
    finally:
        lab.close()
    if not result.reached:
        err = UserError("safe state NOT reached: " + "; ".join(result.problems))
        err.exit_code = 1
        raise err


# --- export ------------------------------------------------------------------------------------------


def cmd_export(args: argparse.Namespace) -> int:
    from labrunner.campaign_csv import write_campaign
    from labrunner.store import Store

    with Store.open_existing(args.db) as store:
        cid = store.resolve(args.campaign)
        frame = store.samples_frame(cid, include_monitor=args.with_monitor)
    if frame.empty:
        raise UserError(f"{args.db}: campaign {cid} has no recorded samples to export")
    target = sys.stdout if str(args.csv) == "-" else args.csv
    write_campaign(frame, target)
    if target is not sys.stdout:
        print(f"wrote {len(frame):,} rows of campaign {cid} to {args.csv}", file=sys.stderr)
    return 0
