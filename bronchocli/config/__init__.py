"""Typed experiments.yaml: one module per job.

* ``sections`` — the settings sections as strict pydantic models (``runs``, ``dataset``, ``train``, ...);
* ``grid`` — the grid, stages and selections, ``expand_grid`` and the cell key (``run_signature``);
* ``schema`` — the whole ``Config``, its validation, what ``tune.space`` may search;
* ``paths`` — every path and URL resolved once (``cfg.paths``), and the checks before anything is written;
* ``messages`` — the text of a config error (every problem at once, file:line, key, value, rule);
* ``loading`` — YAML with line numbers, profiles, ``--set`` overrides, renamed keys (``load_config``).

The names below are the package's public surface; import them from ``bronchocli.config``.
"""

from .grid import RUN_SECTIONS, SELECTABLE, Grid, Select, Stage, cell_key, expand_grid, run_signature
from .loading import DEFAULT_CONFIG, deep_merge, load_config, parse_override
from .paths import Paths, check_dataset_root, check_output, check_paths, check_roots, output_folder
from .schema import TUNABLE, Config, space_problems
from .sections import (
                       CsvColumns,
                       CsvImport,
                       DataCfg,
                       DatasetCfg,
                       EvalCfg,
                       Generate,
                       ModelCfg,
                       Realism,
                       RunsCfg,
                       Section,
                       Splits,
                       Storage,
                       SweepCfg,
                       Train,
                       Tune,
                       TuneParam,
)

__all__ = [
    "DEFAULT_CONFIG", "RUN_SECTIONS", "SELECTABLE", "TUNABLE", "Config", "CsvColumns", "CsvImport", "DataCfg",
    "DatasetCfg", "EvalCfg", "Generate", "Grid", "ModelCfg", "Paths", "Realism", "RunsCfg", "Section", "Select",
    "Splits", "Stage", "Storage", "SweepCfg", "Train", "Tune", "TuneParam", "cell_key", "check_dataset_root",
    "check_output", "check_paths", "check_roots", "deep_merge", "expand_grid", "load_config", "output_folder",
    "parse_override", "run_signature", "space_problems",
]
