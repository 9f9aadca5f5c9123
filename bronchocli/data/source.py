"""The configured dataset: a ``bronchopose`` folder or foreign CSVs, chosen by ``dataset.format``."""

from __future__ import annotations

import json

from ..config import Config
from .importer import csv_patients, import_csv
from .naming import DATASET_JSON
from .reader import Dataset, open_dataset_dir


def open_dataset(cfg: Config) -> Dataset:
    """``dataset.root`` read as ``dataset.format`` ('bronchopose' or 'csv')."""
    if cfg.dataset.format == "csv":
        return import_csv(cfg.paths.dataset, cfg.dataset.csv)
    return open_dataset_dir(cfg.paths.dataset)


def dataset_patients(cfg: Config) -> list[str] | None:
    """The patients of the configured dataset, read cheaply; None when a ``bronchopose`` dataset is not there yet.

    A foreign CSV dataset must exist: its patients come from its CSVs.
    """
    if cfg.dataset.format == "csv":
        return csv_patients(cfg.paths.dataset, cfg.dataset.csv)
    meta = cfg.paths.dataset / DATASET_JSON
    if not meta.is_file():
        return None
    return [str(p) for p in json.loads(meta.read_text())["patients"]]
