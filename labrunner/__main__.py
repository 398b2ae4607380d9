"""`python -m labrunner ...`: the same command line as `labrunner ...`."""

import sys

from labrunner.cli import main

sys.exit(main())
