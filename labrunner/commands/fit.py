"""`labrunner fit`: its arguments. The fit itself is `labrunner.calibration.command.run`, imported when the
command runs: the calibration package loads scipy, pandas and matplotlib, which `labrunner --help` and every
other command must not pay for."""

from __future__ import annotations

import argparse

from labrunner.commands.types import count
from labrunner.store_address import data_arg

# labrunner.calibration.rbf_model.VARIANTS and labrunner.calibration.evaluation.SPLITS, written out: importing
# either loads the calibration package. tests/test_startup_imports.py checks they are the same.
VARIANTS: tuple[str, ...] = ("paper", "triad", "hybrid")
SPLITS: tuple[str, ...] = ("random", "between_temperatures", "beyond_temperatures", "between_rates", "time_blocks")


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "fit", help="fit thermal calibration models (polynomial, RBF network) to a campaign",
        description="Fit the six-position calibration per temperature step, the thermal polynomial and the RBF "
                    "networks to a campaign (CSV or labrunner database), evaluate them on held-out data and "
                    "write the models (JSON, C header). A summary (markdown tables) goes to stdout; with a "
                    "database the fit is stored in it too. docs/calibration.md explains the models.",
        epilog="""\
examples:
  labrunner fit quick.db --out fit/ --json fit.json         # models, C header and tables in fit/
  labrunner fit quick.csv --order cv --rbf hybrid          # polynomial order by cross-validation
  labrunner fit quick.db --json - --quiet | jq .evaluation  # the JSON alone, on stdout""")
    p.add_argument("data", type=data_arg, metavar="DATA",
                   help="campaign CSV or labrunner store (DB: a SQLite file or a PostgreSQL URL)")
    p.add_argument("--campaign", type=int, default=None, metavar="N",
                   help="campaign id in a database holding several (default: the latest)")
    p.add_argument("--json", metavar="FILE", help="write models, evaluation and provenance as JSON ('-' for stdout)")
    p.add_argument("--out", metavar="DIR", help="write model JSON files, the C header and evaluation tables here")
    p.add_argument("--order", default="3", metavar="N",
                   help="polynomial order, or 'cv' to choose it by cross-validation")
    p.add_argument("--poly-method", choices=("joint", "two_stage"), default="joint",
                   help="joint one-stage fit or the paper's two-stage fit")
    p.add_argument("--rbf", default=",".join(VARIANTS), metavar="NAMES",
                   help=f"RBF variants to train, comma-separated from {', '.join(VARIANTS)}")
    p.add_argument("--export-rbf", default=None, metavar="NAME",
                   help="RBF variant exported to the model files (default: hybrid if trained, else the first "
                        "trained)")
    p.add_argument("--splits", default=",".join(SPLITS), metavar="NAMES",
                   help=f"evaluation splits, comma-separated (default: all: {', '.join(SPLITS)})")
    p.add_argument("--thermal-lag", default=None, metavar="TAU_S",
                   help="the sensing element's thermal lag behind its temperature sensor: a time constant TAU_S in "
                        "s, 'from:DIAG.json' (the thermal_lag finding of `labrunner diagnose --json`) or 'auto' "
                        "to search it; the lag-corrected fit is used when it lowers the held-out error (default: "
                        "the logged temperature)")
    p.add_argument("--hysteresis", action="store_true",
                   help="fit per heating/cooling branch (e.g. after the diagnosis's hysteresis finding): the "
                        "outputs less width/2 x the branch state, used per triad when it lowers the held-out "
                        "record error by 15 %% or more on average over the splits (none 5 %% worse) "
                        "(default: one fit for both branches)")
    p.add_argument("--no-eval", action="store_true", help="skip the held-out evaluation")
    p.add_argument("--seed", type=count, default=0, metavar="N", help="seed of the random held-out split")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.add_argument("--no-store", action="store_true",
                   help="with a database: do not store this fit in it (stored by default, with its provenance)")
    p.add_argument("--force", action="store_true",
                   help="overwrite an existing --json file and write into a non-empty --out directory")
    p.set_defaults(func=cmd_fit)


def cmd_fit(args: argparse.Namespace) -> int:
    from labrunner.calibration.command import run

    return run(args)
