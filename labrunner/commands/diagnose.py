"""`labrunner diagnose`: its arguments. The diagnosis itself is `labrunner.discrepancy.command.handler`,
imported when the command runs: the discrepancy package loads scipy and the IMU effects, which
`labrunner --help` and every other command must not pay for."""

from __future__ import annotations

import argparse

from labrunner.store_address import data_arg

# labrunner.discrepancy.terms.CAUSE_ORDER (the causes as the IMU effects register them), written out:
# importing it loads the discrepancy package. tests/test_startup_imports.py checks they are the same.
CAUSE_ORDER: tuple[str, ...] = ("thermal_lag", "hysteresis", "warmup", "turn_on_bias", "g_sensitivity",
                                "scale_nonlinearity", "temperature_nonlinearity", "lever_arm")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "diagnose", help="find what the simulated IMU model gets wrong in measured data, and extend it",
        description="Fit the simulator's IMU error model to a measured campaign (CSV or store), test every "
                    "candidate cause on held-out time blocks, name the ones the data supports, write the "
                    "extended model for the sims and the held-out gain. The verdict and the findings go to "
                    "stdout. It needs a campaign of some length (several held-out stretches of 30 s or more); "
                    "docs/diagnosis.md explains the method and the causes.",
        epilog="""\
examples:
  labrunner diagnose lab.csv --json diagnosis.json --report diagnosis/
  labrunner diagnose quick.db --json d.json --causes thermal_lag,hysteresis""")
    p.add_argument("data", type=data_arg, metavar="DATA",
                   help="campaign CSV or labrunner store (DB: a SQLite file or a PostgreSQL URL)")
    p.add_argument("--json", required=True, dest="json_out", metavar="FILE", help="write the diagnosis JSON here")
    p.add_argument("--report", metavar="DIR", help="also write plots, residuals.csv and summary.md here")
    p.add_argument("--model", metavar="FILE",
                   help="where to write the extended IMU model (default: the --json FILE with .imu_model.json)")
    p.add_argument("--campaign", type=int, metavar="N",
                   help="campaign id in a database holding several (default: the latest)")
    p.add_argument("--causes", metavar="NAMES", help="comma-separated subset of causes to test (default: all: "
                                                     + ", ".join(CAUSE_ORDER) + ")")
    p.add_argument("--min-evidence", type=float, default=10.0, metavar="SCORE",
                   help="held-out evidence a cause must exceed (2 x log-likelihood, after the parameter charge)")
    p.add_argument("--force", action="store_true",
                   help="overwrite existing --json and --model files and write into a non-empty --report directory")
    p.set_defaults(func=cmd_diagnose)


def cmd_diagnose(args: argparse.Namespace) -> int:
    from labrunner.discrepancy.command import handler

    return handler(args)
