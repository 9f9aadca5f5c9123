"""The paper's tables and figures from the MLflow runs of a config's cells (`bronchopose report`).

scope (the config's cells, stages and recorded selections) -> collect (one
batched MLflow query, one run per cell) -> aggregate (replicates and
per-trajectory samples) -> stats (variance-component t intervals, paired t tests, Holm) ->
judge (intervals, reference rows, marks, skill) -> tables (name -> builder
registry) -> markdown / latex renderers; figures from predictions.csv and the
tables (skill, learning curve). See docs/reports.md.
"""

from .collect import RunIndex, RunRecord, collect_runs, index_runs
from .report import ReportResult, collect_index, make_report
from .table_model import Estimate, Table
from .tables import TABLES, ReportContext

__all__ = ["RunIndex", "RunRecord", "collect_runs", "index_runs", "Estimate", "Table", "ReportResult",
           "collect_index", "make_report", "TABLES", "ReportContext"]
