"""`bronchopose ui`: the MLflow UI on 127.0.0.1 for the configured tracking store."""

from __future__ import annotations

import os
import shutil
import socket
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


def check_port(host: str, port: int) -> None:
    """The UI's port must be valid and free on ``host`` (checked here: mlflow would fail with a traceback)."""
    if not 1 <= port <= 65535:
        raise BronchoError(f"--port {port}: must be between 1 and 65535")
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError) as exc:
        raise BronchoError(f"--host {host}: not an address of this machine ({exc})") from None
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server does: TIME_WAIT is no obstacle
        try:
            sock.bind(address)
        except OSError as exc:
            raise BronchoError(f"--port {port}: cannot listen on {host}:{port} ({exc.strerror or exc}); is another "
                               "`bronchopose ui` or MLflow server running? pick another port with --port") from None


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
    check_port(host, port)
    from .. import tracking  # lazy: mlflow loads only when the UI starts

    tracking.check_reachable(cfg)  # `mlflow ui` itself would retry a dead database for minutes
    argv = ui_command(cfg, host, port)
    if not Path(argv[0]).exists():
        raise BronchoError("the `mlflow` executable was not found next to this Python; reinstall bronchocli")
    cfg.paths.artifacts.mkdir(parents=True, exist_ok=True)
    console.print(f"MLflow UI for {urls.redact(cfg.paths.tracking_uri)} at http://{host}:{port} (Ctrl-C to stop)")
    sys.stdout.flush()
    os.execv(argv[0], argv)
