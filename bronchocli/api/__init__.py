"""bronchocli's public Python API: run the platform's work from Python and read typed results, and use a trained
run's model.

Everything here is stable and documented in docs/api.md (with runnable examples that CI executes); the rest of
the package is internal.

Work (``api.work``; the commands are thin layers over these):

* :func:`train` -- one cell as one MLflow run -> :class:`TrainResult`;
* :func:`sweep` -- the config's plan, each cell once, with a launcher -> :class:`SweepResult`;
* :func:`report` -- the paper's tables and figures from the runs -> :class:`ReportResult` (``Table.frame()``:
  a table as a pandas DataFrame);
* :func:`status` -- a sweep's cells, their runs and metrics -> ``SweepState`` (``cells()``);
* :func:`tune` / :func:`study` -- an Optuna study of one cell run, or read -> :class:`StudyResult`.

Inference (``api.inference``):

* :func:`load_model` -- a run's MLflow Model by run id, ``models:/<name>/<version>``,
  ``models:/<name>@<alias>``, ``models:/<model_id>``, ``runs:/<id>/model`` or a local folder;
* :func:`read_frames` / :func:`read_poses` -- uint8 frames ``[T, H, W, 3]`` of a folder, a video or a dataset
  trajectory, and ground-truth poses ``[T, 6]`` of a dataset trajectory or a pose CSV;
* :func:`predict` -- the ``T-1`` relative poses of ``T`` frames, in the model's pose frame;
* :func:`chain` -- relative poses -> absolute trajectory ``[T, 6]`` from a first pose;
* :func:`score` -- per-pair and accumulated errors of a prediction and of both image-blind references.

Poses follow the project's convention (docs/conventions.md): position in voxels, orientation as intrinsic XYZ
Euler angles in degrees.

The command line is a thin layer over this package: every ``bronchopose`` command calls these functions, and
those of ``api.manage`` (the sweep's plan, gc, cancel; ``config``) and ``api.tools`` (data, profile, selftest,
track, ui, weights); ``api.arguments`` holds the names and bounds their arguments take, light enough for the
command line's start-up. Importing ``bronchocli.api`` loads neither torch nor MLflow: the inference half loads
when one of its names is first used.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..training.outcome import TrainResult
from .results import StudyResult, SweepResult
from .work import config_of, report, status, study, sweep, train, tune

__all__ = ["PoseModel", "load_model", "read_frames", "read_poses", "predict", "chain", "score",
           "train", "sweep", "report", "status", "tune", "study", "config_of",
           "StudyResult", "SweepResult", "TrainResult", "ReportResult", "Table"]

if TYPE_CHECKING:
    from ..reporting.report import ReportResult
    from ..reporting.table_model import Table
    from .inference import PoseModel, chain, load_model, predict, read_frames, read_poses, score

INFERENCE = ("PoseModel", "load_model", "read_frames", "read_poses", "predict", "chain", "score")


def __getattr__(name: str) -> Any:
    """The inference half (MLflow, torch) and ``ReportResult``/``Table`` (the reporting stack) load only when one
    of their names is asked for: ``import bronchocli.api`` stays light enough for the command line's start-up."""
    if name in INFERENCE:
        from . import inference  # lazy: MLflow and torch only once the inference half is used

        return getattr(inference, name)
    if name == "ReportResult":
        from ..reporting.report import ReportResult  # lazy: the reporting stack only when asked for

        return ReportResult
    if name == "Table":
        from ..reporting.table_model import Table  # lazy: the reporting stack only when asked for

        return Table
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
