"""`labrunner check`: validate a procedure, a lab configuration, a sim configuration or a campaign CSV."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from labrunner.errors import UserError
from labrunner.store_address import StoreAddress, store_arg

if TYPE_CHECKING:
    from labrunner.lab import LabConfig
    from labrunner.procedure import Procedure


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check", help="validate inputs without running anything",
        description="Validate a procedure (and print its plan: steps, samples, lab time), a lab configuration, a "
                    "sim configuration or a campaign CSV, any of them together. Problems are reported with file, "
                    "line and key (or column); nothing talks to an instrument (except --ping, which only reads). "
                    "Exit code 0 when all are valid, 2 otherwise (1 when a ping fails).",
        epilog="""\
examples:
  labrunner check quick                                     # the shipped quick procedure's plan
  labrunner check procedures/paper_campaign.yaml --lab lab.yaml
  labrunner check --lab lab.yaml --ping                     # talk to the instruments; nothing moves
  labrunner check --sim-config sim.yaml --csv quick.csv
  labrunner check quick --sim                               # also what `run --sim` refuses at its start
  labrunner check --db quick.db                             # the store: pages, JSON and sample blobs""")
    p.add_argument("procedure", type=Path, nargs="?", metavar="PROCEDURE",
                   help="procedure YAML, or the name of a shipped one (quick, paper_campaign)")
    p.add_argument("--lab", type=Path, metavar="LAB.yaml", help="lab configuration naming the instruments")
    p.add_argument("--ping", action="store_true",
                   help="with --lab: connect to each instrument and read identity, limits and a second of IMU "
                        "frames, check gravity (1 g, which axis is up); nothing is moved or written (exit 1 when "
                        "an instrument fails)")
    p.add_argument("--sim-config", type=Path, metavar="SIM.yaml",
                   help="sim configuration (seed, plants, IMU model, faults)")
    p.add_argument("--sim", action="store_true",
                   help="check PROCEDURE as `labrunner run --sim` would start it (the default simulated lab, or "
                        "--sim-config's)")
    p.add_argument("--csv", type=Path, metavar="FILE", help="campaign CSV, as `labrunner export` writes it")
    p.add_argument("--db", type=store_arg, metavar="DB",
                   help="labrunner store (a SQLite file or a PostgreSQL URL): on SQLite its full integrity check; "
                        "then the schema version and every stored JSON column and sample blob decoded; each "
                        "problem named by campaign, table and step (exit 2 when damaged)")
    p.set_defaults(func=cmd_check)


def cmd_check(args: argparse.Namespace) -> int:
    from labrunner import api  # here, not at the top: building the parser must not load the API

    if not (args.procedure or args.lab or args.sim_config or args.csv or args.db):
        raise UserError("nothing to check: give a procedure, --lab, --sim-config, --csv or --db")
    if args.ping and not args.lab:
        raise UserError("--ping talks to the instruments of a lab configuration: give --lab LAB.yaml")
    if args.sim and not args.procedure:
        raise UserError("--sim checks a procedure as `run --sim` would start it: give the procedure")
    if args.procedure:
        p = api.load_procedure(args.procedure)
        steps = p.steps()
        temps = p.model.temperatures.values()
        rates = p.model.rates.values()
        print(f"{args.procedure}: procedure '{p.name}' is valid")
        print(f"  {len(p.orientations())} orientation(s), {len(temps)} temperature(s) {temps[0]:g}..{temps[-1]:g} C "
              f"({p.model.temperatures.order}), {len(rates)} rate step(s) {min(rates):g}..{max(rates):g} deg/s")
        print(f"  {len(steps)} record steps of {p.model.record_s:g} s at {p.model.sample_rate_hz:g} Hz: "
              f"{len(steps) * p.frames_per_record:,} samples; about {p.estimated_duration_s() / 3600:.1f} h of lab "
              "time")
    if args.lab:
        from labrunner.lab import describe_lab_config

        cfg = api.load_lab_config(args.lab)
        print(f"{args.lab}: lab configuration '{cfg.name}' is valid")
        for line in describe_lab_config(cfg):
            print(f"  {line}")
        if args.ping:
            _ping(args.lab, cfg)
    if args.sim_config:
        sim = api.load_sim_config(args.sim_config)
        print(f"{args.sim_config}: sim configuration is valid (seed {sim.seed}, "
              f"IMU effects: {', '.join(sim.imu_model.effects) or 'none'})")
    if args.procedure and (args.lab or args.sim_config or args.sim):
        _check_run(p, args)
    if args.csv:
        f = api.read_campaign_csv(args.csv)
        print(f"{args.csv}: campaign CSV is valid: {len(f):,} rows, {f.run.nunique()} run(s), orientations "
              f"{', '.join(sorted(f.orientation.astype(str).unique()))}, IMU temperature "
              f"{f.imu_temp_c.min():.1f}..{f.imu_temp_c.max():.1f} C, table {f.table_rate_dps.min():g}.."
              f"{f.table_rate_dps.max():g} deg/s")
    if args.db:
        return _check_store(args.db)
    return 0


def _check_run(procedure: Procedure, args: argparse.Namespace) -> None:
    """What `run` would refuse at its start, through the same function `run` calls."""
    from labrunner import api
    from labrunner.run_validation import validate_run
    from labrunner.sim_config import sim_config_dict

    if args.lab:
        validate_run(procedure, lab=api.load_lab_config(args.lab), lab_source=args.lab)
        print(f"{args.procedure}: runs on {args.lab}, as far as can be known without the instruments")
    if args.sim or args.sim_config:
        validate_run(procedure, sim=sim_config_dict(args.sim_config), sim_source=args.sim_config)
        print(f"{args.procedure}: `labrunner run --sim` would start it"
              + (f" with {args.sim_config}" if args.sim_config else ""))


def _ping(path: Path, cfg: LabConfig) -> None:
    """`--ping`: the instruments' answers, one block each; any failure ends the command with exit 1."""
    from labrunner.lab_ping import ping_lab

    report = ping_lab(cfg)
    print(f"{path}: ping (nothing is moved or written)")
    for line in report.lines():
        print(f"  {line}")
    if not report.ok:
        failed = [f"{i.kind}: {i.problem}" for i in report.instruments if i.problem]
        failed += [report.gravity_problem] if report.gravity_problem else []
        err = UserError(f"{path}: ping failed: " + "; ".join(failed))
        err.exit_code = 1
        raise err


def _check_store(db: StoreAddress) -> int:
    """The store's damage, one line each (exit 2), or that it is clean (exit 0)."""
    from labrunner.store import Store

    with Store.open_existing(db, check=False) as store:  # the open's quick_check would stop at the first
        problems = store.damage_report()
        ids = [] if problems else store.campaign_ids()
    if problems:
        print(f"{db}: the store is damaged: {len(problems)} problem{'s' if len(problems) != 1 else ''}")
        for line in problems:
            print(f"  {line}")
        return 2
    pages = ("integrity check ok" if db.file is not None
             else "page-level checks are the PostgreSQL server's job (checksums, amcheck)")
    print(f"{db}: the store is intact: {pages}, schema version ok, {len(ids)} campaign(s), every JSON column and "
          "sample blob readable")
    return 0
