"""The paper's tables and figures from a sweep's MLflow runs (`bronchopose report`).

collect (one batched MLflow query, one run per cell) -> aggregate (pooling over
folds/seeds) -> tables (name -> builder registry) -> model (formatting,
highlighting) -> markdown / latex renderers; figures from predictions.csv
artifacts. See docs/reports.md.
"""

from .collect import RunIndex, RunRecord, collect_runs, index_runs
from .layout import Table
from .report import ReportResult, make_report
from .tables import TABLES, ReportContext

__all__ = ["RunIndex", "RunRecord", "collect_runs", "index_runs", "Table", "ReportResult", "make_report",
           "TABLES", "ReportContext"]
