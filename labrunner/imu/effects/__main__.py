"""`python -m labrunner.imu.effects [--write DOC]`: print the cause table (or update it in DOC)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..cause_table import cause_table, with_table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m labrunner.imu.effects", description=__doc__)
    parser.add_argument("--write", metavar="DOC", help="replace the table between the markers in this file")
    args = parser.parse_args(argv)
    if args.write:
        path = Path(args.write)
        path.write_text(with_table(path.read_text()))
        print(f"cause table written to {path}")
    else:
        sys.stdout.write(cause_table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
