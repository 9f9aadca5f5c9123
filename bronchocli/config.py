"""Typed experiments.yaml: schema, validation with every problem at once, profiles, grid cells.

``load_config(path, profile, overrides)`` reads the YAML, deep-merges the named
profile over it, applies ``--set key.path=value`` overrides, and validates the
result against the frozen pydantic models below (unknown keys rejected). Every
problem is reported in one ``ConfigError`` naming file, line, key path, the bad
value and what is allowed.

``expand_grid(cfg, patients)`` turns ``grid`` into frozen, hashable ``Cell``s
whose ``key`` is a hash of the cell and of every config section that changes
what a run computes, so the same config gives the same key everywhere and a
changed config gives new cells.

Relative paths in the config (dataset root, caches, SQLite URLs) are resolved
against the directory of the config file, not the working directory.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Sequence

import yaml
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from . import cells, registry, urls
from .cells import LOBES, POPULATIONS, ROT_LOSSES, ArchName, Cell, Lobe, Population, PoseFrame, RotLoss, Seed
from .errors import ConfigError

DEFAULT_CONFIG = "experiments.yaml"


class Section(BaseModel):
    # strict: no silent coercion (``steps: true`` is not 1, ``lr: "0.1"`` is not 0.1; ints still fill floats);
    # allow_inf_nan off: ``.inf``/``.nan`` are refused for every float setting.
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


# A YAML list for a fixed-length tuple (strict mode alone wants a tuple, which YAML cannot write).
def _pair(kind: Any, n: int) -> Any:
    return Annotated[tuple[(kind,) * n], Field(strict=False)]  # type: ignore[misc]


def _listify(value: Any) -> Any:
    """Let a grid axis be written as a scalar (``arch: lstm``) as well as a list."""
    return [value] if isinstance(value, (str, int, float)) and not isinstance(value, bool) else value


class Tracking(Section):
    uri: str = "sqlite:///runs/mlflow.db"  # any MLflow tracking URI; ${VAR} is expanded
    experiment: str | None = None  # MLflow experiment name; defaults to the config's name
    artifacts: str = "runs/artifacts"  # artifact root for experiments created on a local store
    checkpoints: str = "runs/checkpoints"  # resumable training state, one folder per unfinished MLflow run
    model_artifact: Literal["fp32", "fp16", "none"] = "fp16"  # the trained weights a FINISHED run keeps in MLflow
    timeout_s: float = Field(10.0, gt=0, le=3600)  # connect/answer limit for tracking servers and databases
    busy_timeout_s: float = Field(60.0, gt=0, le=86400)  # how long a locked/briefly-down database is waited for


class Storage(Section):
    url: str = "sqlite:///runs/sweep.db"  # sweep claims and Optuna studies; ${VAR} is expanded


class Realism(Section):
    texture: bool = True  # procedural mucosa texture on the lumen wall
    specular: float = Field(0.3, ge=0, le=1)
    vignetting: bool = True  # spot-light fall-off towards the image border
    blur: float = Field(0.0, ge=0, le=5)  # Gaussian blur sigma in pixels


class Generate(Section):
    """How ``data generate`` builds a synthetic dataset (also used when ``dataset.root`` is missing)."""

    anatomy: str = "procedural"  # 'procedural' or a path to a .vtu/.vtp/.nii/.nii.gz/.mhd/.nrrd/.stl/.obj file
    centreline: str | None = None  # centreline graph for a surface-mesh anatomy (computed when absent)
    patients: int = Field(3, ge=1)  # procedural patients (seeds seed, seed+1, ...)
    seed: Seed = 0
    lobes: list[Lobe] = list(LOBES)
    lobe_generation: int | None = Field(6, ge=2)  # lobe paths end at this generation (paper: 4-6); None: deepest
    trajectories: int = Field(6, ge=1)  # per patient and lobe
    image_size: int = Field(64, ge=16, le=1024)
    fov_deg: float = Field(70.0, gt=10, lt=170)
    voxel_mm: float = Field(0.5, gt=0)  # world voxel size for procedural anatomies
    offset_voxels: int = Field(2, ge=0)  # position variations in [-k, k] voxels per axis
    roll_deg: float = Field(45.0, ge=0, le=180)  # roll variations in [-r, r] ...
    roll_step_deg: float = Field(15.0, gt=0)  # ... in steps of this
    look_ahead_mm: float = Field(10.0, gt=0)  # the camera looks at the centreline this far ahead
    step_mm: _pair(float, 2) = (1.0, 3.0)  # arc-length increment per frame (speeds), min and max
    base_step_mm: float = Field(0.5, gt=0)  # arc-length grid of base points; increments are multiples of it
    wall_margin_mm: float = Field(0.4, ge=0)  # camera stays this far inside the local lumen radius
    max_frames: int | None = Field(None, ge=2)  # cap on frames per trajectory
    realism: Realism = Realism()
    workers: int = Field(2, ge=1)

    @field_validator("step_mm")
    @classmethod
    def _step_range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not (0 < v[0] <= v[1]):
            raise ValueError("must be [min, max] with 0 < min <= max")
        return v

    @field_validator("base_step_mm")
    @classmethod
    def _base_step(cls, v: float, info: Any) -> float:
        steps = info.data.get("step_mm")
        if steps is not None and v > steps[0]:
            raise ValueError(f"must not exceed step_mm's minimum ({steps[0]}): increments are whole base steps")
        return v


CameraAxis = Literal["x", "y", "z", "-x", "-y", "-z"]


class CsvColumns(Section):
    """Column names of a foreign pose CSV (``dataset.format: csv``)."""

    patient: str | None = "patient"  # None: one patient named after the file
    lobe: str | None = "lobe"  # None: a single lobe for every row
    trajectory: str | None = "trajectory"  # None: one trajectory per patient and lobe
    frame: str | None = "frame"  # None: row order within the trajectory
    x: str = "x"
    y: str = "y"
    z: str = "z"
    rx: str = "rx"  # the three angle columns, in the order of the axes in dataset.csv.euler
    ry: str = "ry"  # (e.g. euler ZYX: rx holds the Z angle, rz the X angle)
    rz: str = "rz"
    filename: str | None = "filename"  # None: poses only (evaluating trajectories; training needs frames)


class CsvImport(Section):
    files: list[str] = []  # CSV paths or globs, relative to dataset.root; empty: every *.csv in it
    frames: str = "."  # directory the filename column is relative to (relative to dataset.root)
    columns: CsvColumns = CsvColumns()
    angle_units: Literal["deg", "rad"] = "deg"
    euler: str = "XYZ"  # SciPy convention of the angle columns (e.g. 'xyz' extrinsic, 'ZYX' intrinsic)
    position_units: Literal["voxel", "mm"] = "voxel"
    spacing_mm: _pair(float, 3) = (1.0, 1.0, 1.0)  # voxel size; mm positions are divided by it
    camera_forward: CameraAxis = "x"  # the imported camera's optical axis (OpenCV-style cameras: z)
    camera_up: CameraAxis = "z"  # its image-up axis (OpenCV-style cameras, y pointing down: -y)

    @model_validator(mode="after")
    def _camera_axes(self) -> "CsvImport":
        if self.camera_forward[-1] == self.camera_up[-1]:
            raise ValueError(f"camera_forward ({self.camera_forward}) and camera_up ({self.camera_up}) must be "
                             "different axes")
        return self

    @field_validator("euler")
    @classmethod
    def _euler(cls, v: str) -> str:
        if not re.fullmatch(r"[xyz]{3}|[XYZ]{3}", v) or v[0] == v[1] or v[1] == v[2]:
            raise ValueError("must be three axes, all upper case (intrinsic) or all lower case (extrinsic), "
                             "no axis twice in a row, e.g. XYZ, ZYX, xyz")
        return v


class DatasetCfg(Section):
    root: str = "data/synthetic"
    format: Literal["bronchopose", "csv"] = "bronchopose"
    generate: Generate = Generate()
    csv: CsvImport = CsvImport()


class Splits(Section):
    train: int = Field(15, ge=1)  # personalized: trajectories per patient and lobe
    val: int = Field(3, ge=1)
    test: int = Field(3, ge=1)
    cross_subject_val: int = Field(3, ge=1)  # cross-subject: val trajectories per training patient and lobe
    seed: Seed = 0


class Grid(Section):
    arch: list[ArchName] = Field(default_factory=lambda: list(registry.arch_names()))  # every one registered
    rot_loss: list[RotLoss] = list(ROT_LOSSES)
    population: list[Population] = list(POPULATIONS)
    folds: Literal["all"] | list[str] = "all"  # cross-subject held-out patients
    seed: list[Seed] = [0, 1, 2]
    pose_frame: list[PoseFrame] = ["world"]
    train_trajectories: list[int | None] = [None]  # training trajectories per patient and lobe (None: splits.train)

    _wrap = field_validator("arch", "rot_loss", "population", "seed", "pose_frame", "folds", "train_trajectories",
                            mode="before")(lambda v: v if v == "all" else _listify(v))

    @field_validator("arch", "rot_loss", "population", "seed", "pose_frame", "train_trajectories")
    @classmethod
    def _not_empty(cls, v: list) -> list:
        if not v:
            raise ValueError("must list at least one value (an empty axis makes an empty grid)")
        if len(set(map(str, v))) != len(v):
            raise ValueError("lists a value twice")
        return v

    @field_validator("train_trajectories")
    @classmethod
    def _positive(cls, v: list) -> list:
        if any(n is not None and n < 1 for n in v):
            raise ValueError("every value must be >= 1 (or null for splits.train)")
        return v


SELECTABLE = ("arch", "rot_loss", "pose_frame", "train_trajectories")  # what a stage's "combination" can be


class Select(Section):
    """Which cells of an earlier stage go on: the ``top`` combinations by a validation metric (never a test one)."""

    top: int = Field(3, ge=1)
    by: str = "val_best.pos_l2"  # a run metric: val_best.<pos_l2|rot_l2|de|ce|loss> or best_val_loss
    over: list[Literal["arch", "rot_loss", "pose_frame", "train_trajectories"]] = ["arch", "rot_loss"]

    @field_validator("by")
    @classmethod
    def _validation_only(cls, v: str) -> str:
        if not (v.startswith("val_best.") or v == "best_val_loss"):
            raise ValueError("must be a validation metric (val_best.pos_l2, val_best.rot_l2, val_best.de, "
                             "val_best.ce, val_best.loss or best_val_loss): selection never looks at test results")
        return v

    @field_validator("over")
    @classmethod
    def _over(cls, v: list) -> list:
        if not v or len(set(v)) != len(v):
            raise ValueError("must list one or more distinct cell fields")
        return v


class Stage(Section):
    """One step of a staged sweep (the paper's three experiments); docs/sweep.md."""

    name: str
    grid: dict[str, Any] = {}  # overrides of the top-level grid for this stage
    select: Select | None = None  # keep the top combinations of ``source`` (their other axes from this grid)
    source: str | None = None  # the stage ``select`` ranks (default: the previous stage)
    add: list[dict[str, Any]] = []  # extra combinations, e.g. {arch: offsetnet, rot_loss: mse}

    @field_validator("name")
    @classmethod
    def _stage_name(cls, v: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_-]*", v):
            raise ValueError("must start with a letter or digit and use only letters, digits, '_', '-'")
        return v

    @field_validator("grid")
    @classmethod
    def _grid(cls, v: dict[str, Any]) -> dict[str, Any]:
        unknown = sorted(set(v) - set(Grid.model_fields))
        if unknown:
            raise ValueError(f"unknown grid key(s) {unknown} (allowed: {', '.join(Grid.model_fields)})")
        return v

    @field_validator("add")
    @classmethod
    def _add(cls, v: list[dict[str, Any]]) -> list[dict[str, Any]]:
        for entry in v:
            unknown = sorted(set(entry) - set(SELECTABLE))
            if unknown:
                raise ValueError(f"{entry}: unknown field(s) {unknown} (allowed: {', '.join(SELECTABLE)})")
        return v

    def stage_grid(self, base: "Grid") -> "Grid":
        return Grid.model_validate({**base.model_dump(), **self.grid})


class DataCfg(Section):
    image_size: int | None = Field(None, ge=16, le=1024)  # network input; None = the dataset's
    window: int = Field(10, ge=1)  # L image pairs per training window of temporal models
    overlap: int = Field(0, ge=0)  # pairs shared by consecutive windows
    workers: int = Field(0, ge=0)  # frame cache decoding threads (0: one per core, at most 8)
    cache_dir: str = "runs/cache"  # decoded-frame cache (uint8, memory-mapped)
    frames_on_device: Literal["auto", "yes", "no"] = "auto"  # CUDA: keep the whole frame cache in GPU memory
    augment: bool = False  # photometric augmentation of training frames

    @field_validator("overlap")
    @classmethod
    def _overlap(cls, v: int, info: Any) -> int:
        window = info.data.get("window")
        if window is not None and v >= window:
            raise ValueError(f"must be smaller than data.window ({window}): consecutive windows share this many pairs")
        return v


class ModelCfg(Section):
    dropout: float = Field(0.2, ge=0, lt=1)  # inside the ShuffleNet blocks
    pretrained: str | None = None  # None: random init; "imagenet": torchvision's weights (hub cache); or a local file
    channels_last: bool = True


class Train(Section):
    """The training budget and optimiser; docs/training.md explains each choice."""

    steps: int = Field(400, ge=1)  # optimiser steps: the budget, identical for every cell of a sweep
    batch_size: int = Field(20, ge=1)  # image pairs per micro-batch (temporal models: batch_size / window windows)
    effective_batch: int | None = Field(None, ge=1)  # image pairs per optimiser step (gradient accumulation)
    lr: float = Field(1e-3, gt=0)
    weight_decay: float = Field(0.0, ge=0)  # > 0: AdamW (decoupled), else Adam
    warmup: float = Field(0.05, ge=0, lt=1)  # fraction of the steps with a linear learning-rate warm-up
    schedule: Literal["cosine", "constant"] = "cosine"  # after the warm-up
    val_every: int = Field(50, ge=1)  # steps between validations (best weights, early stopping, pruning)
    patience: int | None = Field(None, ge=1)  # validations without improvement before stopping; None: never
    min_delta: float = Field(0.0, ge=0)
    standardize_labels: bool = True  # predict (pose - train mean) / train std; undone at prediction
    bn_recalibrate: int = Field(16, ge=0)  # training batches that re-estimate BatchNorm statistics per validation
    tbptt_chunks: int = Field(1, ge=1)  # K chunks of L pairs per training sequence
    rot_weight: float = Field(1.0, ge=0)
    precision: Literal["auto", "32", "16-mixed", "bf16-mixed"] = "auto"
    device: Literal["auto", "cpu", "cuda", "mps"] = "auto"
    # torch.compile the network: false, true (= default) or an inductor mode; reduce-overhead captures the
    # forward and backward in CUDA graphs (docs/training.md, "GPU"; benchmarks/README.md)
    compile: bool | Literal["default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs"] = False
    max_val_pairs: int | None = Field(None, ge=1)  # cap on validation pairs (evenly spread, the same every time)
    threads: int | None = Field(None, ge=1)  # torch CPU threads; None = all cores / sweep workers

    @model_validator(mode="after")
    def _accumulation(self) -> "Train":
        if self.effective_batch is not None and self.effective_batch % self.batch_size:
            raise ValueError(f"effective_batch ({self.effective_batch}) must be a multiple of batch_size "
                             f"({self.batch_size}): each optimiser step sums whole micro-batches")
        return self

    @property
    def pairs_per_step(self) -> int:
        """Image pairs behind each optimiser step (micro-batch x accumulation)."""
        return self.effective_batch or self.batch_size


class EvalCfg(Section):
    """Camera-tracking metrics of the test evaluation (odometry.py; docs/reports.md, tracking table)."""

    ctf_position: float = Field(5.0, gt=0)  # voxels: a frame is tracked below this position error ...
    ctf_position_mm: float = Field(5.0, gt=0)  # ... (ctf_mm: the same in mm, from the dataset's voxel spacing)
    ctf_angle: float = Field(10.0, gt=0, le=180)  # ... and below this rotation error (degrees, geodesic)
    rpe_gap: int = Field(10, ge=1)  # frames between the two poses of a relative pose error


class TuneParam(Section):
    type: Literal["float", "int", "categorical"]
    low: float | None = None
    high: float | None = None
    log: bool = False
    step: float | None = None
    choices: list[Any] | None = None


class Tune(Section):
    trials: int = Field(20, ge=1)
    timeout: float | None = Field(None, gt=0)
    sampler: Literal["tpe", "random"] = "tpe"
    seed: Seed = 0
    pruner: Literal["median", "hyperband", "none"] = "median"
    warmup_validations: int = Field(1, ge=0)  # validations a trial always runs before it may be pruned
    startup_trials: int = Field(2, ge=0)  # trials before TPE models and the median pruner prunes
    applied: str | None = None  # set by --use-tuned: "optuna:<study>#<trial>" whose best values this config holds
    space: dict[str, TuneParam] = {
        "train.lr": TuneParam(type="float", low=1e-5, high=1e-3, log=True),
        "model.dropout": TuneParam(type="float", low=0.0, high=0.5),
    }


class SweepCfg(Section):
    max_retries: int = Field(1, ge=0)  # automatic re-runs of a FAILED cell (a lost worker counts as a failure)
    heartbeat_s: float = Field(10.0, gt=0)  # a worker refreshes its claim this often
    stale_after_s: float = Field(60.0, gt=0)  # a claim without heartbeat this long is reclaimed
    poll_s: float = Field(2.0, gt=0)  # an idle worker looks again this often (cells held elsewhere)
    logs: str = "runs/sweep-logs"  # one log file per worker process
    launcher: Literal["local", "slurm"] = "local"  # slurm: submit array tasks as workers (slurm section)

    @field_validator("stale_after_s")
    @classmethod
    def _stale(cls, v: float, info: Any) -> float:
        beat = info.data.get("heartbeat_s")
        if beat is not None and v < 2 * beat:
            raise ValueError(f"must be at least twice sweep.heartbeat_s ({beat:g}): a live worker must never look stale")
        return v


# sbatch options the Slurm launcher sets itself: ``slurm.additional`` may not override them (docs/cluster.md)
SLURM_MANAGED = ("array", "job-name", "comment", "output", "error", "open-mode", "signal", "requeue", "no-requeue",
                 "gres", "gpus-per-task", "cpus-per-task", "mem", "time", "partition", "account", "qos",
                 "dependency", "parsable", "wrap", "export", "chdir")


class SlurmCfg(Section):
    """``bronchopose sweep --launcher slurm``: every array task is one sweep worker (docs/cluster.md).

    Names follow Hydra's submitit launcher where one exists (timeout_min, cpus_per_task, mem_gb,
    array_parallelism, setup, additional, signal_delay_s)."""

    partition: str | None = None
    account: str | None = None
    qos: str | None = None
    timeout_min: int = Field(60, ge=1)  # --time of every array task
    gpus_per_task: int = Field(1, ge=0)  # --gres=gpu:N; Slurm sets each task's CUDA_VISIBLE_DEVICES
    cpus_per_task: int = Field(2, ge=1)  # also the worker's torch threads (train.threads unset)
    mem_gb: float | None = Field(None, gt=0)  # --mem per task; None: the cluster's DefMemPerCPU
    tasks: int | None = Field(None, ge=1)  # array tasks (workers) at most per stage; None: one per cell left
    array_parallelism: int = Field(256, ge=1)  # tasks of one array running at once (--array=0-N%K)
    signal_delay_s: int = Field(120, ge=1)  # SIGUSR1 this long before the time limit: checkpoint, requeue
    setup: list[str] = []  # shell lines run before the worker (module load, source venv/bin/activate)
    additional: dict[str, str | int | bool] = {}  # more sbatch options, e.g. {constraint: a100, exclusive: true}
    python: str | None = None  # interpreter of the workers; None: the one running bronchopose sweep
    logs: str = "runs/slurm-logs"  # per-task logs, <logs>/<array job>_<task>.log (appended across requeues)
    shared_filesystem: bool = False  # opt-in: SQLite/file stores and node-local paths are seen by every node
    exit_when_idle: bool = True  # a task with nothing it can claim exits instead of holding its GPU

    @field_validator("partition", "account", "qos")
    @classmethod
    def _slurm_name(cls, v: str | None) -> str | None:
        if v is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._,-]*", v):
            raise ValueError("must be a Slurm name: letters, digits, '.', '_', '-' (',' separates several)")
        return v

    @field_validator("setup")
    @classmethod
    def _setup(cls, v: list[str]) -> list[str]:
        if any("\n" in line for line in v):
            raise ValueError("each entry is one shell line (no newline inside); list several lines instead")
        return v

    @field_validator("additional")
    @classmethod
    def _additional(cls, v: dict[str, Any]) -> dict[str, Any]:
        for key in v:
            name = key.replace("_", "-")
            if not re.fullmatch(r"[a-z][a-z0-9-]*", name):
                raise ValueError(f"{key!r}: must be an sbatch long option name without dashes, e.g. constraint")
            if name in SLURM_MANAGED:
                raise ValueError(f"{key!r}: set by the launcher itself (or by its own slurm key); not allowed here")
        return v


@dataclass(frozen=True)
class Paths:
    """Every path and URL of a config, resolved once (``${VAR}``, ``~``, relative to the config's folder)."""

    base: Path
    dataset: Path
    cache: Path
    checkpoints: Path
    artifacts: Path
    sweep_logs: Path
    pretrained: Path | str | None  # "imagenet" stays the literal name (models/pretrained.py)
    anatomy: Path | None  # None: procedural
    centreline: Path | None
    tracking_uri: str
    storage_url: str

    @classmethod
    def of(cls, cfg: "Config", base: Path) -> "Paths":
        def path(p: str | None) -> Path | None:
            if p is None:
                return None
            q = Path(os.path.expandvars(p)).expanduser()
            return q if q.is_absolute() else (base / q).resolve()

        gen = cfg.dataset.generate
        return cls(
            base=base, dataset=path(cfg.dataset.root), cache=path(cfg.data.cache_dir),
            checkpoints=path(cfg.tracking.checkpoints), artifacts=path(cfg.tracking.artifacts),
            sweep_logs=path(cfg.sweep.logs),
            pretrained=cfg.model.pretrained if cfg.model.pretrained == "imagenet" else path(cfg.model.pretrained),
            anatomy=None if gen.anatomy == "procedural" else path(gen.anatomy), centreline=path(gen.centreline),
            tracking_uri=urls.resolve(cfg.tracking.uri, base), storage_url=urls.resolve(cfg.storage.url, base),
        )


class Config(Section):
    name: str
    tracking: Tracking = Tracking()
    storage: Storage = Storage()
    dataset: DatasetCfg = DatasetCfg()
    splits: Splits = Splits()
    grid: Grid = Grid()
    stages: list[Stage] = []  # a staged plan (the paper's protocol); empty: run ``grid`` as one stage
    data: DataCfg = DataCfg()
    model: ModelCfg = ModelCfg()
    train: Train = Train()
    eval: EvalCfg = EvalCfg()
    tune: Tune = Tune()
    sweep: SweepCfg = SweepCfg()
    slurm: SlurmCfg = SlurmCfg()
    profiles: dict[str, dict[str, Any]] = {}

    _paths: Paths | None = PrivateAttr(default=None)
    _source: str = PrivateAttr(default="<memory>")
    _profile: str | None = PrivateAttr(default=None)

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", v):
            raise ValueError("must start with a letter or digit and use only letters, digits, '.', '_', '-'")
        return v

    @model_validator(mode="after")
    def _stages(self) -> "Config":
        names = [st.name for st in self.stages]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"stages: stage name(s) {dupes} used twice")
        for i, st in enumerate(self.stages):
            try:
                st.stage_grid(self.grid)
            except ValidationError as exc:
                first = exc.errors()[0]
                raise ValueError(f"stages[{i}] ({st.name}).grid.{'.'.join(map(str, first['loc']))}: {first['msg']}"
                                 ) from None
            if st.source is not None and st.source not in names[:i]:
                raise ValueError(f"stages[{i}] ({st.name}).source {st.source!r}: must name an earlier stage "
                                 f"({', '.join(names[:i]) or 'none before it'})")
            if st.select is not None and i == 0:
                raise ValueError(f"stages[0] ({st.name}).select: the first stage has no earlier stage to select from")
        return self

    @property
    def paths(self) -> Paths:
        """Every path and URL, resolved against the config file's folder when it was loaded."""
        if self._paths is None:
            self._paths = Paths.of(self, Path.cwd())
        return self._paths

    @property
    def profile(self) -> str | None:
        return self._profile

    @property
    def experiment_name(self) -> str:
        return self.tracking.experiment or self.name

    def cell(self, **coords: Any) -> Cell:
        """A validated cell of this config, with its key (ConfigError naming the bad field otherwise).

        No ``pose_frame`` (or None): the first of ``grid.pose_frame``, the frame the config's plan trains in.
        """
        if coords.get("pose_frame") is None:
            coords["pose_frame"] = self.grid.pose_frame[0]
        bare = cells.make(**coords)
        return bare.model_copy(update={"key": cell_key(self, bare.coords())})

    def dump(self) -> dict[str, Any]:
        """The resolved config as plain data (profiles dropped: they are already applied)."""
        data = self.model_dump(mode="json")
        data.pop("profiles")
        return data

    def to_yaml(self) -> str:
        """The config as YAML, every URL password shown as ``***``."""
        return urls.redact(yaml.safe_dump(self.dump(), sort_keys=False))

    def with_values(self, values: dict[str, Any]) -> "Config":
        """A validated copy with dotted-path values set, e.g. ``{"train.lr": 1e-3}``."""
        raw = self.model_dump(mode="json")
        for key, value in values.items():
            _set_path(raw, key, value, where=f"override {key}")
        space = any(k == "tune" or k.startswith("tune.space") for k in values)  # else checked when it loaded
        return _validate(raw, self._source, {}, self.paths.base, self._profile, space=space)


TUNABLE = ("data", "model", "train", "splits", "dataset")  # the sections ``tune.space`` may search


def space_problems(cfg: Config) -> list[str]:
    """What is wrong with ``tune.space``: each key a settable run setting, each distribution well formed."""
    problems = []
    for path, p in cfg.tune.space.items():
        where = f"tune.space.{path}"
        if path.split(".")[0] not in TUNABLE:
            problems.append(f"{where}: only run settings can be tuned ({', '.join(TUNABLE)})")
            continue
        if p.type == "categorical" and not p.choices:
            problems.append(f"{where}: categorical needs a non-empty 'choices' list")
            continue
        if p.type != "categorical" and (p.low is None or p.high is None or not p.low < p.high):
            problems.append(f"{where}: {p.type} needs low < high (got low={p.low}, high={p.high})")
            continue
        if p.log and p.type != "categorical" and p.low <= 0:
            problems.append(f"{where}: log scale needs low > 0 (got {p.low})")
            continue
        if p.step is not None and p.step <= 0:
            problems.append(f"{where}: step must be > 0 (got {p.step})")
            continue
        probes = p.choices if p.type == "categorical" else [p.low, p.high]
        for value in probes:  # every choice (and both ends of a range) must be a valid value of the setting
            value = int(value) if p.type == "int" else value
            raw = cfg.model_dump(mode="json")
            try:
                _set_path(raw, path, value, where=where)
                _validate(raw, cfg._source, {}, cfg.paths.base, cfg._profile, space=False)
            except ConfigError as exc:
                last = str(exc).splitlines()[-1].strip().removeprefix("invalid config: ")
                problems.append(f"{where}: {last.partition(': ')[2] or last}")
                break
    return problems


# -- loading ------------------------------------------------------------------


def _set_path(data: dict[str, Any], dotted: str, value: Any, where: str) -> None:
    parts = dotted.split(".")
    node = data
    for part in parts[:-1]:
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        if not isinstance(child, dict):
            raise ConfigError(f"{where}: '{part}' in '{dotted}' is a value, not a section")
        node = child
    node[parts[-1]] = value


def parse_override(text: str) -> tuple[str, Any]:
    """``key.path=value`` -> (path, YAML-parsed value)."""
    key, sep, raw = text.partition("=")
    if not sep or not re.fullmatch(r"[A-Za-z_][\w-]*(\.[\w-]+)*", key.strip()):
        raise ConfigError(urls.redact(f"--set {text!r}: expected key.path=value, e.g. --set train.lr=3e-4"))
    try:
        _check_structure(yaml.compose(raw, Loader=_UniqueKeyLoader), f"--set {key.strip()}")  # noqa: S506
        value = yaml.load(raw, Loader=_UniqueKeyLoader) if raw.strip() else None  # noqa: S506 - SafeLoader
    except _DuplicateKey as exc:
        raise ConfigError(urls.redact(f"--set {text!r}: duplicate key {exc.key!r}")) from None
    except yaml.YAMLError:
        value = raw
    return key.strip(), value


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def _line_index(node: yaml.Node, source: str, prefix: tuple = ()) -> dict[tuple, str]:
    """Key path -> ``file:line`` where it is written, from a composed YAML node tree."""
    where = {prefix: f"{source}:{node.start_mark.line + 1}"}
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:
            where.update(_line_index(value_node, source, prefix + (str(key_node.value),)))
            where[prefix + (str(key_node.value),)] = f"{source}:{key_node.start_mark.line + 1}"
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            where.update(_line_index(item, source, prefix + (i,)))
    return where


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, key: Any, line: int, first: int):
        super().__init__(f"duplicate key {key!r}")
        self.key, self.line, self.first = key, line, first


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, except that a key written twice in one mapping is an error (PyYAML keeps the last),
    in block and flow style alike, and ``1e-5`` is a number (YAML 1.2; PyYAML's 1.1 rules read it as text)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, tuple[int, int]] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # ``<<: *anchor`` may repeat and is overridden by design
                continue
            key = self.construct_object(key_node, deep=True)
            mark = key_node.start_mark
            try:
                first = seen.setdefault(key, (mark.index, mark.line + 1))
            except TypeError:  # an unhashable key: the base class reports it
                continue
            if first[0] != mark.index:  # the position, not the line: ``{lr: 1, lr: 2}`` is one line
                raise _DuplicateKey(key, mark.line + 1, first[1])
        return super().construct_mapping(node, deep)


_UniqueKeyLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))

MAX_YAML_VALUES = 100_000  # a config past this many values (after aliases expand) is an alias bomb, not a config


def _check_structure(node: yaml.Node | None, source: str) -> None:
    """Refuse a recursive alias (an anchor used inside itself) and an alias bomb, naming the line."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(n: yaml.Node) -> int:
        if id(n) in sizes:
            return sizes[id(n)]
        if id(n) in active:
            raise ConfigError(f"{source}:{n.start_mark.line + 1}: recursive YAML alias (an anchor used inside "
                              "itself); write the values out instead")
        active.add(id(n))
        children = ([c for pair in n.value for c in pair] if isinstance(n, yaml.MappingNode) else
                    list(n.value) if isinstance(n, yaml.SequenceNode) else [])
        total = 1 + sum(size(c) for c in children)
        active.discard(id(n))
        if total > MAX_YAML_VALUES:
            raise ConfigError(f"{source}:{n.start_mark.line + 1}: YAML aliases expand to more than "
                              f"{MAX_YAML_VALUES:,} values; a config this large is not a config")
        sizes[id(n)] = total
        return total

    if node is not None:
        size(node)


def _read_text(path: Path) -> str:
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the config ({exc.strerror or exc})") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); save the config as "
                          "UTF-8") from None


def _read_yaml(path: Path) -> tuple[dict[str, Any], dict[tuple, str]]:
    text = _read_text(path)
    try:
        node = yaml.compose(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
        _check_structure(node, str(path))
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except _DuplicateKey as exc:
        raise ConfigError(f"{path}:{exc.line}: duplicate key {exc.key!r} (first written at line {exc.first}); "
                          "each key may appear once per section") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{where}: YAML syntax error: {problem}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections at the top level, got {type(data).__name__}")
    return data, (_line_index(node, str(path)) if node is not None else {})


def _allowed_keys(loc: tuple) -> list[str]:
    model: Any = Config
    for part in loc[:-1]:
        field = getattr(model, "model_fields", {}).get(part)
        if field is None:
            return []
        model = field.annotation
    return sorted(getattr(model, "model_fields", {}))


def _describe(error: dict[str, Any]) -> str:
    loc = tuple(error["loc"])
    if error["type"] == "extra_forbidden":
        allowed = _allowed_keys(loc)
        return f"unknown key {loc[-1]!r}" + (f" (allowed: {', '.join(allowed)})" if allowed else "")
    if error["type"] == "missing":
        return "required key is missing"
    value = error.get("input")
    shown = json.dumps(value, default=str) if not isinstance(value, dict) else "a mapping"
    msg = error["msg"]
    if error["type"] == "literal_error":
        msg = f"must be one of {error['ctx']['expected']}"
    return f"{shown}: {msg[0].lower() + msg[1:]}"


def _format_errors(exc: ValidationError, source: str, lines: dict[tuple, str]) -> str:
    problems = []
    for error in exc.errors():
        loc = tuple(p for p in error["loc"] if not (isinstance(p, str) and p.startswith(("literal[", "list["))))
        error = {**error, "loc": loc}
        path = ".".join(str(p) if isinstance(p, str) else f"[{p}]" for p in loc).replace(".[", "[") or "<top>"
        where = next((lines[loc[:n]] for n in range(len(loc), -1, -1) if loc[:n] in lines), source)
        problems.append(f"{where}: {path}: {_describe(error)}")
    unique = list(dict.fromkeys(problems))
    if len(unique) == 1:  # one problem, one line
        return urls.redact(f"invalid config: {unique[0]}")  # a bad value may hold a URL password
    head = f"invalid config ({len(unique)} problems):"
    return urls.redact("\n".join([head, *("  " + p for p in unique)]))


def _validate(raw: dict[str, Any], source: str, lines: dict[tuple, str], base: Path, profile: str | None,
              space: bool = True) -> Config:
    try:
        cfg = Config.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(_format_errors(exc, source, lines)) from None
    cfg._source, cfg._profile = source, profile
    cfg._paths = Paths.of(cfg, base)
    problems = space_problems(cfg) if space else []
    if problems:  # the same check as `tune`, so `config` never calls a space valid that tune refuses
        where = next((v for k, v in lines.items() if k[:2] == ("tune", "space")), source)
        shown = [f"{where}: {p}" for p in problems]
        raise ConfigError(urls.redact(f"invalid config: {shown[0]}" if len(shown) == 1 else
                                      "\n".join([f"invalid config ({len(shown)} problems):",
                                                  *("  " + p for p in shown)])))
    return cfg


def _blame_override(lines: dict[tuple, str], key: tuple, where: str) -> None:
    """Problems at or under an overridden key, and at sections it created, are the override's, not the file's."""
    for k in [k for k in lines if k[: len(key)] == key]:
        del lines[k]
    lines[key] = where
    for n in range(1, len(key)):
        lines.setdefault(key[:n], where)


def load_config(
    path: str | os.PathLike = DEFAULT_CONFIG,
    profile: str | None = None,
    overrides: Sequence[str] = (),
) -> Config:
    """Load, merge profile and ``--set`` overrides, and validate ``experiments.yaml``."""
    path = Path(path)
    raw, lines = _read_yaml(path)
    if profile is not None:
        profiles = raw.get("profiles") or {}
        if profile not in profiles:
            names = ", ".join(sorted(profiles)) or "none defined"
            raise ConfigError(f"{path}: profiles.{profile}: no such profile (available: {names})")
        if not isinstance(profiles[profile], dict):
            raise ConfigError(f"{path}: profiles.{profile}: must be a mapping of overrides")
        raw = deep_merge(raw, profiles[profile])
        prefix = ("profiles", profile)
        lines = {**lines, **{k[2:]: v for k, v in lines.items() if k[:2] == prefix}}
    for text in overrides:
        key, value = parse_override(text)
        _set_path(raw, key, value, where=f"--set {text}")
        _blame_override(lines, tuple(key.split(".")), f"--set {text}")
    return _validate(raw, str(path), lines, path.resolve().parent, profile)


# -- grid ---------------------------------------------------------------------


# Sections that change what a run computes; tracking, storage, tune, sweep, slurm and
# profiles do not, so moving the MLflow store never invalidates finished cells.
RUN_SECTIONS = ("dataset", "splits", "data", "model", "train")


# Settings that change how fast a run goes, not what it computes.
NOT_IN_KEY = (("train", "threads"), ("train", "compile"), ("data", "workers"), ("data", "cache_dir"),
              ("data", "frames_on_device"))


def run_signature(cfg: Config) -> dict[str, Any]:
    data = cfg.model_dump(mode="json")
    sig = {k: data[k] for k in RUN_SECTIONS}
    for section, key in NOT_IN_KEY:
        sig[section].pop(key, None)
    return sig


def cell_key(cfg: Config, coords: dict[str, Any]) -> str:
    blob = json.dumps({"cell": coords, "config": run_signature(cfg)}, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def expand_grid(cfg: Config, patients: Sequence[str] | None = None, grid: Grid | None = None) -> list[Cell]:
    """Every cell of ``grid`` (default ``cfg.grid``), in a stable order.

    ``patients`` (the dataset's patient ids) is needed when cross-subject folds
    are ``all``; listed folds must be among them when it is given.
    """
    g = grid or cfg.grid
    folds: list[str] = []
    if "cross-subject" in g.population:
        if g.folds == "all":
            if patients is None:
                raise ConfigError("grid.folds: 'all' needs the dataset's patient list (generate or point at a dataset first)")
            folds = list(patients)
        else:
            folds = list(g.folds)
            unknown = [f for f in folds if patients is not None and f not in patients]
            if unknown:
                raise ConfigError(f"grid.folds: {unknown} not in the dataset's patients ({', '.join(patients)})")
    out = []
    for population in g.population:
        for fold in (folds if population == "cross-subject" else [None]):
            for arch, rot_loss, size, seed, frame in itertools.product(g.arch, g.rot_loss, g.train_trajectories,
                                                                        g.seed, g.pose_frame):
                out.append(cfg.cell(arch=arch, rot_loss=rot_loss, population=population, fold=fold, seed=seed,
                                    pose_frame=frame, train_trajectories=size))
    return out
