"""The study report: one self-contained HTML page per subject (see :mod:`cystomap.report.stage`)."""

from cystomap.report.config import ReportConfig
from cystomap.report.data import ComparisonInputs, SessionInputs
from cystomap.report.stage import build_report

__all__ = ["ComparisonInputs", "ReportConfig", "SessionInputs", "build_report"]
