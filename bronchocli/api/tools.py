"""The platform's other commands as calls: a dataset (``data generate | stats | preview``), the machine
(``profile``, ``selftest``), a trained model on new frames (``track``), the MLflow UI (``ui``) and backbone weights
(``weights install``). Each checks what it was given before any expensive work (one
:class:`~bronchocli.errors.BronchoError` line) and prints only to the console it is given.

The stacks they need (torch, VTK, MLflow, pandas, matplotlib) load inside each call, never when this module is
imported.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path

from rich.console import Console

from .. import pathcheck
from ..config import DEFAULT_CONFIG, Config, parse_override
from ..errors import BronchoError, ConfigError
from ..extras import require
from .work import config_of


def _silent() -> Console:
    return Console(quiet=True)


def config_or_defaults(config: str | os.PathLike = DEFAULT_CONFIG, profile: str | None = None,
                       overrides: Sequence[str] = (), name: str = "bronchopose") -> Config:
    """``config_of``, except that without an experiments.yaml (the default path missing, no profile) the defaults
    apply, named ``name``, with the overrides: work on a dataset alone needs no config file."""
    if Path(config) == Path(DEFAULT_CONFIG) and not Path(config).exists() and not profile:
        return Config(name=name).with_values(dict(parse_override(s) for s in overrides))
    return config_of(config, profile, overrides)


def output_path(path: str | os.PathLike, flag: str, kind: str = "folder") -> Path:
    """``path`` (``~`` expanded) checked as a ``folder`` (or a ``file``) to write by the one check every output goes
    through (``pathcheck.check_output``: no system folder, the right kind, creatable); creates nothing."""
    path = Path(path).expanduser()
    pathcheck.check_output(path, flag, kind)
    return path


# -- data ---------------------------------------------------------------------------------------------------------


def generate(config: str | os.PathLike = DEFAULT_CONFIG, *, anatomy: str | None = None, patients: int | None = None,
             image_size: int | None = None, trajectories: int | None = None, seed: int | None = None,
             out: str | os.PathLike | None = None, workers: int | None = None, progress: bool = True,
             profile: str | None = None, overrides: Sequence[str] = (), console: Console | None = None) -> None:
    """``data generate``: render the configured synthetic dataset (``dataset.generate``; the arguments override
    it, a bad value reported like any other override); resumable, a folder of another config refused."""
    require("render", "data generate", ("vtkmodules",))
    from ..generation import entry  # lazy: VTK loads only when rendering

    values = {k: v for k, v in dict(patients=patients, image_size=image_size, trajectories=trajectories,
                                    seed=seed).items() if v is not None}
    if anatomy is not None:  # a path given here is relative to the working directory, not to the config file
        values["anatomy"] = anatomy if anatomy == "procedural" else str(pathcheck.resolve(anatomy, "--anatomy"))
    flags = [f"dataset.generate.{k}={json.dumps(v)}" for k, v in values.items()]
    cfg = config_or_defaults(config, profile, [*overrides, *flags], "data-generate")
    entry.generate(cfg, Path(out) if out is not None else None, workers=workers, progress=progress,
                   console=console or _silent())


def data_stats(config: str | os.PathLike = DEFAULT_CONFIG, *, dataset: str | os.PathLike | None = None,
               population: str | None = None, fold: str | None = None, manifest: str | os.PathLike | None = None,
               profile: str | None = None, overrides: Sequence[str] = (), console: Console | None = None) -> None:
    """``data stats``: counts, lengths and pose ranges of ``dataset`` (default: the config's ``dataset.root``),
    with ``population`` (and ``fold``) its split under the config's ``splits``; ``manifest``: that split as CSV."""
    from ..data import entry  # lazy: pandas only when a dataset is read

    if manifest is not None and population is None:
        raise ConfigError("--manifest needs --population (personalized or cross-subject)")
    # Inspecting a dataset should not need an experiments.yaml: without one, the defaults apply.
    if dataset is None:
        cfg = config_of(config, profile, overrides)
    else:
        cfg = config_or_defaults(config, profile, overrides, "data-stats")
        cfg = cfg.with_values({"dataset.root": str(pathcheck.resolve(dataset, "--dataset"))})
    entry.stats(cfg, population=population, fold=fold, manifest=Path(manifest) if manifest is not None else None,
                console=console or _silent())


def preview(dataset: str | os.PathLike, *, out: str | os.PathLike | None = None, columns: int = 6,
            pdf: bool = False) -> list[Path]:
    """``data preview``: a montage of sample frames (``out``, default ``reports/<dataset>-montage.png``) and a 3-D
    plot of the camera positions beside it (``<stem>-positions``); ``pdf``: both as PDF too. The files written."""
    from ..reporting.dataset_figures import preview as draw  # lazy: matplotlib only when drawing

    root = pathcheck.resolve(dataset, "--dataset")
    target = Path(out) if out is not None else Path("reports") / f"{root.name}-montage.png"
    if target.is_dir():
        raise BronchoError(f"--out {target}: is a folder; give the montage's file name, e.g. {target / 'montage.png'}")
    if target.suffix.lower() not in (".png", ".pdf"):
        target = target.with_suffix(".png")
    output_path(target, "--out", "file")  # the montage file itself (its folder may be /tmp)
    formats = ["png", "pdf"] if pdf else [target.suffix.lstrip(".").lower()]
    return draw(root, target, columns=columns, formats=formats)


# -- the machine: profile, selftest ------------------------------------------------------------------------------


def profile(arch: Sequence[str] = ("all",), *, image_size: int | None = None, device: str = "cpu",
            full: bool = False, batch: int | None = None, repeats: int | None = None, warmup: int | None = None,
            window: int = 10, precision: str = "32", channels_last: bool = True, threads: int | None = None,
            fmt: str = "table", speed: str | os.PathLike | None = None, steps: int = 50,
            backbone: str | None = None, frozen_stages: int = 0,
            console: Console | None = None, err_console: Console | None = None) -> None:
    """``profile``: parameters, GMAC, latency and peak memory per architecture (quick unless ``full``); with
    ``speed`` (a file) instead the training speed per setting, the fastest per architecture written there
    (``frozen_stages`` > 0: the training on a cached prefix of that many stages of ``backbone``, its own entry)."""
    if fmt not in ("table", "json"):
        raise BronchoError(f"--format {fmt!r}: must be table or json")
    from ..diagnostics import entry  # lazy: torch loads only when profiling

    console, err_console = console or _silent(), err_console or console or _silent()
    if speed is not None:
        entry.speed(list(arch), Path(speed), device=device, image_size=image_size or 128, pairs=batch or 10,
                    steps=steps, threads=threads, console=console, err_console=err_console, backbone=backbone,
                    frozen_stages=frozen_stages)
        return
    if backbone or frozen_stages:
        raise BronchoError("--backbone and --frozen-stages are options of --speed (the training measured); "
                           "give --speed FILE")
    entry.profile(list(arch), fmt=fmt, threads=threads, console=console, err_console=err_console,
                  image_size=image_size or 256, device=device, batch=batch or (8 if full else 2),
                  repeats=repeats or (10 if full else 3), warmup=(2 if full else 1) if warmup is None else warmup,
                  window=window, precision=precision, channels_last=channels_last)


def selftest(device: str = "auto", precision: str = "auto", arch: Sequence[str] | None = None, *,
             threads: int | None = None, console: Console | None = None) -> int:
    """``selftest``: this machine's training path checked (environment, short trainings, resume, numerics,
    speed); the exit code (0 every check passed, 1 some failed)."""
    from ..diagnostics import entry  # lazy: torch loads only when the checks run

    return entry.selftest(device, precision, arch, threads=threads or 1, console=console or _silent())


def learn(config: str | os.PathLike | Config = DEFAULT_CONFIG, arch: Sequence[str] | None = None,
          rot_loss: str = "ce", *, steps: int = 100, threads: int | None = None, profile: str | None = None,
          overrides: Sequence[str] = (), console: Console | None = None) -> int:
    """``selftest --learn``: can each architecture (default convlstm) memorise 30 training pairs of the configured
    dataset, evaluation reproducing training? The exit code (1 when one cannot)."""
    from ..diagnostics import entry  # lazy: torch loads only when training

    return entry.learn(config_of(config, profile, overrides), list(arch or ["convlstm"]), rot_loss, steps=steps,
                       threads=threads, console=console or _silent())


# -- a trained model on new frames, the UI, weights --------------------------------------------------------------


def track(input_path: str | os.PathLike, *, run: str | None = None, model: str | None = None,
          best: str | None = None, first_pose: str | None = None, ground_truth: str | os.PathLike | None = None,
          out: str | os.PathLike | None = None, register: str | None = None, progress: bool = True,
          config: str | os.PathLike = DEFAULT_CONFIG, profile: str | None = None, overrides: Sequence[str] = (),
          console: Console | None = None) -> None:
    """``track``: apply one model (a ``run``'s, a ``model`` URI, or the ``best`` run of a report table by the
    headline) to a folder of frames, a video or a dataset trajectory: trajectory CSV and plot in ``out``, with
    ground truth (a dataset trajectory, or ``ground_truth``) also the errors."""
    from ..inference import entry, reader, trajectory  # lazy: MLflow (~1 s) only once tracking

    console = console or _silent()
    chosen = [f for f, v in (("--run", run), ("--model", model), ("--best", best)) if v]
    if len(chosen) != 1:
        raise BronchoError(f"give exactly one of --run, --model, --best (got {', '.join(chosen) or 'none'})")
    first = trajectory.parse_pose(first_pose) if first_pose is not None else None
    input_path = Path(input_path)
    inp = reader.open_input(input_path)
    name = "-".join(input_path.parts[-3:]) if inp.kind == "trajectory" else (input_path.stem or "input")
    folder = output_path(out if out is not None else Path("track") / name, "--out")
    truth = reader.read_ground_truth(ground_truth) if ground_truth is not None else None
    cfg = config_of(config, profile, overrides)
    client = None
    if best:  # a report table's choice: resolved here, reporting sits above inference
        from ..reporting.best import best_run  # lazy: the report's run collection only for --best
        from ..runs.client import client_for, require_store

        require_store(cfg)
        client = client_for(cfg)
        chosen_best = best_run(client, cfg, best)
        console.print(chosen_best.describe())
        run = chosen_best.run.run_id
    entry.track(cfg, inp, run or model, folder, first_pose=first, truth=truth, register=register,
                progress=progress, console=console, client=client)


def serve_ui(config: str | os.PathLike = DEFAULT_CONFIG, *, host: str = "127.0.0.1", port: int = 5000,
             workers: int | None = None, expose: bool = False, allowed: Sequence[str] = (),
             warn: Callable[[str], None] | None = None, profile: str | None = None, overrides: Sequence[str] = (),
             console: Console | None = None) -> None:
    """``ui``: the MLflow UI for the config's tracking store on ``host`` (another than 127.0.0.1 only with
    ``expose``), its runs-table link printed; becomes the server (never returns)."""
    from ..runs import ui as mlflow_ui  # lazy: mlflow loads only when the UI starts

    mlflow_ui.serve(config_of(config, profile, overrides), host, port, workers, console or _silent(),
                    expose=expose, allowed=allowed, warn=warn)


def install_weights(path: str | os.PathLike) -> tuple[str, Path]:
    """``weights install``: torchvision's ImageNet weights file ``path`` copied where ``model.pretrained: imagenet``
    reads it (checked: torchvision's checksum, the backbone's keys and shapes); its backbone kind and destination."""
    from ..models.pretrained import install_weights as install  # lazy: torch loads only when installing

    return install(path)


def table_names() -> list[str]:
    """The report's tables (``report --table``'s choices, with ``all``): read when asked, not at start-up."""
    from ..reporting.tables import TABLES  # lazy: the reporting stack loads only when the tables are listed

    return ["all", *TABLES]
