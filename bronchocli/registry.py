"""The named choices and measures, one place each: architectures, rotation losses and metrics.

Everything that lists architectures reads this module: the cell's validation
(``cells.py``: the grid, ``--only``, ``train --arch``, MLflow tags), the model
builder (``models.build_model`` resolves ``ArchSpec.builder``), profiling
(``bronchopose profile --arch all``), the report tables and figures (row
labels, row order, which tables show it) and docs/models.md. Adding an
architecture is a model file in ``models/`` and one :func:`register` call at
the end of this module; no other file lists architecture names.

Rotation losses (:func:`register_rot_loss`) and metrics (:func:`register_metric`)
work the same way: a function (in ``metrics.py``, ``odometry.py`` or any file)
and one registration here. A rotation loss is then a value of the grid,
``train --rot-loss``, ``--only`` and a row label of the report; a metric is
logged by every test evaluation (``pair.<m>``/``acc.<m>`` or ``traj.<m>``),
written to ``trajectory_errors.csv``, validated during training where
``validation`` says so, and a column of the report tables its ``tables`` name,
with its label, unit and direction (docs/architecture.md, "Where a new piece
goes").

The module imports nothing heavy (no torch), so the low layers (cells,
config) can read it. A builder or a function is therefore named, not
imported: a ``"module:attr"`` path inside ``bronchocli.models`` that ``models``
resolves when it first builds one (tests/models checks every path), a function
name of ``metrics.py`` (per-pose metrics, rotation losses) or ``odometry.py``
(per-trajectory metrics) that those modules resolve, or the callable itself (a
test's toy architecture, loss or metric).

What a model *is* (``temporal``, ``recurrent``, ``backbone_kind``) stays a
class attribute of its ``PoseNet`` subclass: the forward code reads it there,
and a copy here could disagree with it.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from .errors import BronchoError

NAME = re.compile(r"[a-z][a-z0-9_]*")  # a cell value, an MLflow tag value and a CLI choice: plain lower case


@dataclass(frozen=True)
class ArchSpec:
    """One architecture: its name, where its model class is, and how the paper and the reports show it."""

    name: str  # the cell's ``arch`` (config grid, ``--arch``, ``--only arch=``, MLflow tag)
    builder: str | Callable[..., Any]  # "module:Class" of a models.PoseNet subclass, or the class itself
    label: str  # its row label in the report tables ("+ConvRNN": what the paper adds to the baseline)
    model_name: str  # the architecture in prose ("ConvLSTM"; a model's name is :func:`model_name`'s)
    paper_params_m: str | None = None  # the paper's parameter count at 256x256, millions, as printed (tested)
    paper_tables: bool = True  # a row group of the personalized / cross-subject tables (OffsetNet: not one)
    paper_row: int | None = None  # its row in the paper's tables; None: after those, in registration order
    named: tuple[tuple[str, str], ...] = ()  # (rot_loss, name): the paper's name of this model with that loss


@dataclass(frozen=True)
class RotLossSpec:
    """One rotation loss: its name, label and per-pose function ``(pred, gt) -> (...)``."""

    name: str  # the cell's ``rot_loss``
    label: str  # its label in the report tables: position loss + rotation loss
    function: str | Callable[..., Any]  # a per-pose function of metrics.py by name, or the function itself
    # In the labels' own units (deg^2): with standardised labels the function is called with ``scale=`` the
    # angles' std, so it weighs like the position term. Bounded angular losses (DE, CE) are never scaled.
    scaled: bool = False


Per = Literal["pose", "trajectory"]


@dataclass(frozen=True)
class MetricSpec:
    """One metric: how it is computed, and how the logs, the CSVs and the report name, show and judge it.

    ``per="pose"``: ``function(pred, gt) -> (...)`` on pose 6-vectors (torch, metrics.py), one value per pose;
    the test evaluation logs ``pair.<name>`` (over pairs) and ``acc.<name>`` (trajectory endpoints).
    ``per="trajectory"``: ``function(errors: odometry.TrackErrors) -> float``, one value per test trajectory;
    logged as ``traj.<name>``. A name ending in ``_mm`` is the millimetre twin of the metric without it.
    """

    name: str  # the MLflow key part and the trajectory_errors.csv column part: stable once runs are logged
    function: str | Callable[..., Any]  # metrics.py (pose) / odometry.py (trajectory) function name, or itself
    per: Per
    unit: str  # in prose ("voxels", "degrees", "unitless"); "%" is a share, bounded 0-100 (logit intervals)
    label: str  # its column heading in the report ("Position L2")
    symbol: str = ""  # the unit in a column heading ("vox", "°"; "" for none)
    higher_is_better: bool = False  # CTF: the best row is the highest, † means not above the reference
    # The report tables that show it: "paper" (Tables 2-6), "ablation", "skill" (skill columns and figures),
    # "frames" (Table 8), "tracking" (Table 9); the column order is the registration order.
    tables: tuple[str, ...] = ()
    validation: bool = False  # also computed at every validation: ``val.<name>``, ``val_best.<name>`` (select.by)
    spacing: bool = False  # pose metrics: needs the dataset's voxel spacing (mm); left out where it is unknown
    short_label: str = ""  # the label where the column says more beside it ("Position skill, world")


TABLE_GROUPS = ("paper", "ablation", "skill", "frames", "tracking")

_ARCHS: dict[str, ArchSpec] = {}  # in registration order: the grid's default order, the CLI's choices


def _check_name(kind: str, name: str, taken: dict[str, Any], reserved: str = "") -> None:
    if not NAME.fullmatch(name) or name == reserved:
        raise BronchoError(f"{kind} name {name!r}: must be lower case letters, digits and '_'")
    if name in taken:
        raise BronchoError(f"{kind} {name!r} is registered already")


def register(spec: ArchSpec) -> ArchSpec:
    """Add an architecture (the one place a new one is named); BronchoError for a bad or taken name."""
    _check_name("architecture", spec.name, _ARCHS, reserved="all")  # "all": every architecture to `profile`
    _ARCHS[spec.name] = spec
    return spec


def arch_names() -> tuple[str, ...]:
    """Every registered architecture, in registration order."""
    return tuple(_ARCHS)


def arch(name: str) -> ArchSpec:
    """The spec of architecture ``name``; KeyError when none is registered under it."""
    return _ARCHS[name]


PAPER_BACKBONE = "efficientnet_b0"  # the paper's backbone: a model on it is named without a suffix
BACKBONE_PARAM = "model.backbone"  # the run param naming the backbone (absent on runs logged before it: the paper's)
BACKBONE_NAMES = {"efficientnet_lite0": "Lite0"}  # a backbone's short name in a model's name (else its key)


def _init_words(init: str | None) -> str:
    """A run's ``init`` tag in a model's name: "ImageNet", "random", or the weight file's name."""
    if not init:
        return ""
    if init.startswith("imagenet:"):
        return "ImageNet"
    if init.startswith("file:"):
        return init.removeprefix("file:").split("#", 1)[0]
    return init


def model_name(arch: str, rot_loss: str, backbone: str | None = None, init: str | None = None) -> str:
    """THE name of a model, wherever one is shown: table rows, figure legends, the UI's run names and run and
    model descriptions, LaTeX. The paper's names: its own name where the paper gives one ("BronchoTrack" for
    ConvLSTM + MSE+CE, "OffsetNet" with its MSE loss: ``ArchSpec.named``), else its row label in the paper's
    Tables 2-3 and its loss ("+ConvRNN MSE+DE", "Baseline MSE+MSE"). A backbone other than the paper's
    (``backbone`` None or ``PAPER_BACKBONE``: none) adds it and the initialisation (the run's ``init`` tag):
    "BronchoTrack · Lite0 ImageNet", "+LSTM MSE+CE · Lite0 random". An unregistered architecture or loss (an
    old run's tag) is shown as it is."""
    spec = _ARCHS.get(arch)
    loss = _ROT_LOSSES[rot_loss].label if rot_loss in _ROT_LOSSES else rot_loss
    name = dict(spec.named).get(rot_loss, "") if spec is not None else ""
    name = name or f"{spec.label if spec is not None else arch} {loss}"
    if backbone and backbone != PAPER_BACKBONE:
        name += " · " + " ".join(w for w in (BACKBONE_NAMES.get(backbone, backbone), _init_words(init)) if w)
    return name


def grouped_label(arch: str, rot_loss: str, backbone: str | None = None, init: str | None = None) -> str:
    """A model's row label under its architecture's group (Tables 2-5, 9: "+ConvRNN" | "MSE+DE"), read from
    :func:`model_name`: the rest of its name after the group, or, for a model the paper names, its loss with the
    name ("MSE+CE (BronchoTrack)"), so the row shows the paper's labels and the model's one name."""
    name = model_name(arch, rot_loss, backbone, init)
    group = f"{_ARCHS[arch].label} " if arch in _ARCHS else f"{arch} "
    if name.startswith(group):
        return name[len(group):]
    loss = _ROT_LOSSES[rot_loss].label if rot_loss in _ROT_LOSSES else rot_loss
    return f"{loss} ({name})"


def table_order() -> list[ArchSpec]:
    """The architectures in the report tables' row order: the paper's rows, then the rest as registered."""
    order = list(_ARCHS.values())
    return sorted(order, key=lambda s: (s.paper_row is None, s.paper_row or 0, order.index(s)))


_ROT_LOSSES: dict[str, RotLossSpec] = {}  # in registration order: the grid's default, the tables' row order
_METRICS: dict[str, MetricSpec] = {}  # in registration order: logging, CSV and table column order


def register_rot_loss(spec: RotLossSpec) -> RotLossSpec:
    """Add a rotation loss (the one place a new one is named); BronchoError for a bad or taken name."""
    _check_name("rotation loss", spec.name, _ROT_LOSSES)
    _ROT_LOSSES[spec.name] = spec
    return spec


def rot_loss_names() -> tuple[str, ...]:
    """Every registered rotation loss, in registration order (the paper's Table 2 order first)."""
    return tuple(_ROT_LOSSES)


def rot_loss(name: str) -> RotLossSpec:
    """The spec of rotation loss ``name``; KeyError when none is registered under it."""
    return _ROT_LOSSES[name]


def register_metric(spec: MetricSpec) -> MetricSpec:
    """Add a metric (the one place a new one is named); BronchoError for a bad or taken name or table."""
    _check_name("metric", spec.name, _METRICS)
    unknown = sorted(set(spec.tables) - set(TABLE_GROUPS))
    if unknown or spec.per not in ("pose", "trajectory"):
        raise BronchoError(f"metric {spec.name!r}: per must be pose or trajectory and tables among "
                           f"{', '.join(TABLE_GROUPS)} (got per={spec.per!r}, tables={list(spec.tables)})")
    _METRICS[spec.name] = spec
    return spec


def metric(name: str) -> MetricSpec:
    """The spec of metric ``name``; KeyError when none is registered under it."""
    return _METRICS[name]


def metric_specs(per: Per | None = None, table: str | None = None, validation: bool | None = None
                 ) -> tuple[MetricSpec, ...]:
    """The registered metrics, in registration order, restricted to one ``per``, one report ``table`` group and
    (with ``validation``) to those computed, or not, at every validation."""
    return tuple(s for s in _METRICS.values() if (per is None or s.per == per)
                 and (table is None or table in s.tables) and (validation is None or s.validation == validation))


def metric_names(per: Per | None = None, table: str | None = None, validation: bool | None = None
                 ) -> tuple[str, ...]:
    """The names of :func:`metric_specs`."""
    return tuple(s.name for s in metric_specs(per, table, validation))


def resolve(spec: RotLossSpec | MetricSpec, namespace: dict[str, Any]) -> Callable[..., Any]:
    """A loss's or metric's function: itself, or the one its name names in ``namespace`` (the ``globals()`` of
    metrics.py or odometry.py)."""
    return spec.function if callable(spec.function) else namespace[spec.function]


# -- the rotation losses of the paper (its Table 2 order; metrics.py) ------------------------------------

register_rot_loss(RotLossSpec("mse", "MSE+MSE", "rot_mse", scaled=True))
register_rot_loss(RotLossSpec("de", "MSE+DE", "direction_error"))
register_rot_loss(RotLossSpec("ce", "MSE+CE", "cosine_error"))


# -- the metrics (docs/training.md; per pose: metrics.py, per trajectory: odometry.py) ----------------------

# Per pose: the paper's four (Tables 2-6), the mm twin of position L2 and the geodesic angle (figures, CSVs).
register_metric(MetricSpec("pos_l2", "pos_l2", "pose", "voxels", "Position L2", "vox",
                           tables=("paper", "ablation", "skill", "frames"), validation=True, short_label="Position"))
register_metric(MetricSpec("pos_l2_mm", "pos_l2_mm", "pose", "mm", "Position L2", "mm", spacing=True))
register_metric(MetricSpec("rot_l2", "rot_l2", "pose", "degrees", "Rotation L2", "°",
                           tables=("paper", "skill", "frames"), validation=True, short_label="Rotation"))
register_metric(MetricSpec("de", "direction_error", "pose", "radians", "DE", "rad", tables=("paper",),
                           validation=True))
register_metric(MetricSpec("ce", "cosine_error", "pose", "unitless", "CE", tables=("paper", "ablation"),
                           validation=True))
register_metric(MetricSpec("geodesic", "geodesic", "pose", "degrees", "Geodesic", "°"))

# Per trajectory: camera tracking as the literature scores it (Table 9).
register_metric(MetricSpec("ctf", "ctf", "trajectory", "%", "CTF vox", "%", higher_is_better=True,
                           tables=("tracking",)))
register_metric(MetricSpec("ctf_mm", "ctf_mm", "trajectory", "%", "CTF mm", "%", higher_is_better=True,
                           tables=("tracking",)))
register_metric(MetricSpec("ate", "ate", "trajectory", "voxels", "ATE", "vox", tables=("tracking",)))
register_metric(MetricSpec("ate_mm", "ate_mm", "trajectory", "mm", "ATE", "mm", tables=("tracking",)))
register_metric(MetricSpec("rpe_trans", "rpe_trans", "trajectory", "voxels", "RPE trans.", "vox",
                           tables=("tracking",)))
register_metric(MetricSpec("rpe_rot", "rpe_rot", "trajectory", "degrees", "RPE rot.", "°", tables=("tracking",)))
register_metric(MetricSpec("drift", "drift", "trajectory", "% of path", "Drift", "% path", tables=("tracking",)))


# -- the architectures (docs/models.md) ---------------------------------------------------------------------

register(ArchSpec("baseline", "bronchocli.models.baseline:BaselineNet", label="Baseline", model_name="Baseline",
                  paper_params_m="13.967", paper_row=1))
register(ArchSpec("lstm", "bronchocli.models.lstm:LSTMNet", label="+LSTM", model_name="LSTM",
                  paper_params_m="14.164", paper_row=2))
register(ArchSpec("convlstm", "bronchocli.models.convlstm:ConvLSTMNet", label="+ConvRNN", model_name="ConvLSTM",
                  paper_params_m="14.142", paper_row=4, named=(("ce", "BronchoTrack"),)))
register(ArchSpec("conv3d", "bronchocli.models.conv3d:Conv3dNet", label="+3D", model_name="3D conv",
                  paper_params_m="13.983", paper_row=3))
# Sganga et al. 2019 as the BronchoPose authors ran it: the sota and ablation tables, not Tables 2-5.
register(ArchSpec("offsetnet", "bronchocli.models.offsetnet:OffsetNet", label="OffsetNet", model_name="OffsetNet",
                  paper_params_m="43.6", paper_tables=False, paper_row=5, named=(("mse", "OffsetNet"),)))
