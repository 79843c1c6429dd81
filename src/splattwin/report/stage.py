"""The report stage as the pipeline runs it: `run(ReportInputs) -> ReportResult` (TWIN/report/index.html,
built from the artifacts every stage wrote; `splattwin.report.build`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class ReportInputs:
    twin_dir: Path
    timings: dict[str, float] = field(default_factory=dict)        # stage -> seconds (this run)
    peak_rss_gib: dict[str, float] = field(default_factory=dict)   # stage -> peak memory
    skipped: list[str] | None = None   # the stages this run found up to date (None: not known)


@dataclass
class ReportResult:
    report: Path       # the self-contained HTML report


def run(inputs: ReportInputs, options=None, *, progress: bool = True) -> ReportResult:
    """options: `report.options.ReportOptions` (None: its defaults)."""
    from splattwin.report.build import build_report

    return ReportResult(report=build_report(inputs.twin_dir, timings=inputs.timings or None,
                                            peak_rss_gib=inputs.peak_rss_gib or None, options=options,
                                            skipped=inputs.skipped))
