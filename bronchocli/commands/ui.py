"""`bronchopose ui`: the MLflow UI on 127.0.0.1 for the configured tracking store."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import typer

from .. import urls
from ..config import DEFAULT_CONFIG
from ..errors import BronchoError
from .common import ConfigOpt, ProfileOpt, SetOpt, console, load


def ui_command(cfg, host: str, port: int) -> list[str]:
    """The `mlflow ui` argv serving the config's store and artifact root."""
    exe = shutil.which("mlflow") or str(Path(sys.executable).with_name("mlflow"))
    argv = [exe, "ui", "--backend-store-uri", cfg.paths.tracking_uri, "--host", host, "--port", str(port)]
    if not urls.is_server(cfg.paths.tracking_uri):
        argv += ["--default-artifact-root", cfg.paths.artifacts.as_uri()]
    return argv


def ui(
    port: int = typer.Option(5000, "--port", help="Port to listen on."),
    host: str = typer.Option("127.0.0.1", "--host", help="Interface (127.0.0.1 keeps it local)."),
    config: ConfigOpt = Path(DEFAULT_CONFIG),
    profile: ProfileOpt = None,
    set_: SetOpt = None,
) -> None:
    """Start the MLflow UI for the config's tracking store (Ctrl-C stops it).

    Runs are grouped in the experiment named by the config; filter them with e.g.
    `tags.arch = 'convlstm' and tags.population = 'personalized'`.
    """
    cfg = load(config, profile, set_)
    if urls.is_server(cfg.paths.tracking_uri):
        raise BronchoError(f"tracking.uri {urls.redact(cfg.paths.tracking_uri)} is already a server: open it in a browser")
    argv = ui_command(cfg, host, port)
    if not Path(argv[0]).exists():
        raise BronchoError("the `mlflow` executable was not found next to this Python; reinstall bronchocli")
    cfg.paths.artifacts.mkdir(parents=True, exist_ok=True)
    console.print(f"MLflow UI for {urls.redact(cfg.paths.tracking_uri)} at http://{host}:{port} (Ctrl-C to stop)")
    sys.stdout.flush()
    os.execv(argv[0], argv)
