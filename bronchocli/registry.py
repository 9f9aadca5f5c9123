"""The named choices of a cell, one place each: the architectures and the rotation losses.

Everything that lists architectures reads this module: the cell's validation
(``cells.py``: the grid, ``--only``, ``train --arch``, MLflow tags), the model
builder (``models.build_model`` resolves ``ArchSpec.builder``), profiling
(``bronchopose profile --arch all``), the report tables and figures (row
labels, row order, which tables show it) and docs/models.md. Adding an
architecture is a model file in ``models/`` and one :func:`register` call at
the end of this module; no other file lists architecture names.

The module imports nothing heavy (no torch), so the low layers (cells,
config) can read it. A builder is therefore named, not imported: a
``"module:attr"`` path inside ``bronchocli.models`` that ``models`` resolves
when it first builds one (tests/models checks every path), or the callable
itself (a test's toy architecture).

What a model *is* (``temporal``, ``recurrent``, ``backbone_kind``) stays a
class attribute of its ``PoseNet`` subclass: the forward code reads it there,
and a copy here could disagree with it.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .errors import BronchoError

NAME = re.compile(r"[a-z][a-z0-9_]*")  # a cell value, an MLflow tag value and a CLI choice: plain lower case


@dataclass(frozen=True)
class ArchSpec:
    """One architecture: its name, where its model class is, and how the paper and the reports show it."""

    name: str  # the cell's ``arch`` (config grid, ``--arch``, ``--only arch=``, MLflow tag)
    builder: str | Callable[..., Any]  # "module:Class" of a models.PoseNet subclass, or the class itself
    label: str  # its row label in the report tables ("+ConvRNN": what the paper adds to the baseline)
    model_name: str  # its name in prose and in the sota row ("BronchoTrack (ConvLSTM, MSE+CE)")
    paper_params_m: str | None = None  # the paper's parameter count at 256x256, millions, as printed (tested)
    paper_tables: bool = True  # a row group of the personalized / cross-subject tables (OffsetNet: not one)
    paper_row: int | None = None  # its row in the paper's tables; None: after those, in registration order


@dataclass(frozen=True)
class RotLossSpec:
    """One rotation loss: its name and label; the function is ``metrics.<function>``."""

    name: str  # the cell's ``rot_loss``
    label: str  # its label in the report tables: position loss + rotation loss
    function: str  # the per-pose function of metrics.py that computes it


_ARCHS: dict[str, ArchSpec] = {}  # in registration order: the grid's default order, the CLI's choices


def register(spec: ArchSpec) -> ArchSpec:
    """Add an architecture (the one place a new one is named); BronchoError for a bad or taken name."""
    if not NAME.fullmatch(spec.name) or spec.name == "all":  # "all" means every architecture to `profile`
        raise BronchoError(f"architecture name {spec.name!r}: must be lower case letters, digits and '_'")
    if spec.name in _ARCHS:
        raise BronchoError(f"architecture {spec.name!r} is registered already")
    _ARCHS[spec.name] = spec
    return spec


def arch_names() -> tuple[str, ...]:
    """Every registered architecture, in registration order."""
    return tuple(_ARCHS)


def arch(name: str) -> ArchSpec:
    """The spec of architecture ``name``; KeyError when none is registered under it."""
    return _ARCHS[name]


def table_order() -> list[ArchSpec]:
    """The architectures in the report tables' row order: the paper's rows, then the rest as registered."""
    order = list(_ARCHS.values())
    return sorted(order, key=lambda s: (s.paper_row is None, s.paper_row or 0, order.index(s)))


# The three rotation losses of the paper (its Table 2 order).
ROT_LOSSES: tuple[RotLossSpec, ...] = (
    RotLossSpec("mse", "MSE+MSE", "rot_mse"),
    RotLossSpec("de", "MSE+DE", "direction_error"),
    RotLossSpec("ce", "MSE+CE", "cosine_error"),
)


# -- the architectures (docs/models.md) ---------------------------------------------------------------------

register(ArchSpec("baseline", "bronchocli.models.baseline:BaselineNet", label="Baseline", model_name="Baseline",
                  paper_params_m="13.967", paper_row=1))
register(ArchSpec("lstm", "bronchocli.models.lstm:LSTMNet", label="+LSTM", model_name="LSTM",
                  paper_params_m="14.164", paper_row=2))
register(ArchSpec("convlstm", "bronchocli.models.convlstm:ConvLSTMNet", label="+ConvRNN", model_name="ConvLSTM",
                  paper_params_m="14.142", paper_row=4))
register(ArchSpec("conv3d", "bronchocli.models.conv3d:Conv3dNet", label="+3D", model_name="3D conv",
                  paper_params_m="13.983", paper_row=3))
# Sganga et al. 2019 as the BronchoPose authors ran it: the sota and ablation tables, not Tables 2-5.
register(ArchSpec("offsetnet", "bronchocli.models.offsetnet:OffsetNet", label="OffsetNet", model_name="OffsetNet",
                  paper_params_m="43.6", paper_tables=False, paper_row=5))
