"""The campaign report: one self-contained HTML file (`labrunner report DB --html FILE`)."""

from .document import SECTIONS, ReportResult, write_report

__all__ = ["SECTIONS", "ReportResult", "write_report"]
