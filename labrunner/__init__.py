"""labrunner: thermal-calibration campaigns for MEMS IMUs.

The Python API (docs/api.md) is `labrunner.api`, re-exported here: `labrunner.run`, `resume`,
`abort`, `status`, `open`, `fit`, `diagnose`, ... It is loaded on first use, so `import labrunner`
stays cheap (the CLI's start-up and `labrunner --version` do not pay for pandas or the sims).
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from labrunner.errors import UserError
from labrunner.version import __version__

# labrunner's records go nowhere until the application configures logging (labrunner.logs.configure,
# called by the CLI); without a handler, Python's last-resort one would print warnings to stderr.
logging.getLogger(__name__).addHandler(logging.NullHandler())

if TYPE_CHECKING:
    from labrunner.api import (
        AbortResult,
        Campaign,
        CampaignStatus,
        CampaignSummary,
        Database,
        Event,
        NextStep,
        OutputPathError,
        Progress,
        RunResult,
        Session,
        abort,
        check_output,
        diagnose,
        fit,
        list_campaigns,
        load_data,
        load_lab_config,
        load_procedure,
        load_sim_config,
        open,
        read_campaign_csv,
        report,
        resume,
        run,
        serve_sim,
        start_resume,
        start_run,
        status,
        write_fit,
    )

__all__ = [
    "AbortResult", "Campaign", "CampaignStatus", "CampaignSummary", "Database", "Event", "NextStep", "OutputPathError",
    "Progress", "RunResult", "Session", "UserError", "__version__", "abort", "check_output", "diagnose", "fit",
    "list_campaigns", "load_data", "load_lab_config", "load_procedure", "load_sim_config", "open",
    "read_campaign_csv", "report", "resume", "run", "serve_sim", "start_resume", "start_run", "status", "write_fit",
]
_API = frozenset(__all__) - {"UserError", "__version__"}  # what __getattr__ loads from labrunner.api


def __getattr__(name: str) -> Any:
    if name in _API:
        from labrunner import api

        return getattr(api, name)
    raise AttributeError(f"module 'labrunner' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | _API)
