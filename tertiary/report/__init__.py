"""The self-contained HTML report of a run (plotly), built from the run store."""

from tertiary.report.html import REPORT_FILENAME, build_report, build_sections, figure_count, render_report

__all__ = ["REPORT_FILENAME", "build_report", "build_sections", "figure_count", "render_report"]
