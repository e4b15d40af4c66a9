"""Report of finished runs: figures, Markdown/LaTeX tables and ``report.md`` from the tidy tables.

`build_report` is imported on first use (PEP 562): figure workers import only `plots`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from locretrieval.report.build import build_report

__all__ = ["build_report"]


def __getattr__(name: str) -> Any:
    if name != "build_report":
        raise AttributeError(f"module 'locretrieval.report' has no attribute {name!r}")
    from locretrieval.report.build import build_report

    return build_report


def __dir__() -> list[str]:
    return sorted([*globals(), "build_report"])
