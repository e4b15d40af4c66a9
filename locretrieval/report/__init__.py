"""Report of finished runs: figures, Markdown/LaTeX tables and ``report.md`` from the tidy tables."""

from locretrieval.report.build import build_report

__all__ = ["build_report"]
