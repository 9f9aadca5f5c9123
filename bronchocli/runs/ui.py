"""The MLflow UI on this machine for the config's tracking store, opened on the runs table (``bronchopose ui``).

It listens on 127.0.0.1 unless asked with ``--expose`` (``check_host``): MLflow's UI has no authentication.

MLflow 3 opens an experiment on its GenAI overview; the link printed here is the
experiment's runs table in the model-training view (``runs_table_url``).
Experiments are created tagged ``mlflow.experimentKind=custom_model_development``,
but MLflow 3.17's UI does not read that tag, nor anything else of the server, for
what it shows first: the mode, an experiment's table state, a run's chart layout
and its Assistant panel are the browser's ``localStorage``. So the server is
MLflow's app with a script of ours first in its page (``uiapp``, loaded as
MLflow's ``mlflow.app`` plugin ``bronchopose``: ``mlflow ui --app-name
bronchopose``, nothing in MLflow patched) that stores, where the browser has
none, the model-training mode, the headline view as the experiment's table
state, the Assistant closed and, for a run's page, its curves first: whatever
address a fresh browser opens, it and MLflow's own navigation (Experiments, then
the experiment) land on the headline view, and a run's "Model metrics" open on
its training and validation curves (issues 36.5, 48.5). The UI's bare address
lands on the runs table. Where the plugin is not registered (bronchocli
installed before it existed) the server is plain `mlflow ui` and a warning says
to reinstall.
The link names the saved view
``views.headline_view`` (stored as an experiment tag here, before the server
starts, in MLflow's saved-view envelope, so the runs table's Views menu lists it
by name): the trained runs sorted by the headline, best first, with the headline
figures as columns (4 significant digits), and a Chart view that opens on the
training and validation curves, then the headline figures a point per run
(``views.chart_sections``). The server is sized for the machine:
``workers`` (default: half the cores, 1 to 4) and no GenAI job runner
(``MLFLOW_SERVER_ENABLE_JOB_EXECUTION=false``: its task consumers serve LLM
judges and trace jobs that a training experiment never uses) and no AI Gateway
(``MLFLOW_ENABLE_AI_GATEWAY=false``: MLflow's documented switch of its endpoints
and UI). No documented setting of MLflow 3.17 hides the "Traces" entries of a
model-training experiment and run (docs/training.md, "Links to GenAI pages").
"""

from __future__ import annotations

import importlib.metadata
import ipaddress
import os
import re
import shutil
import socket
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from rich.console import Console

from .. import urls
from ..config import Config
from ..errors import BronchoError
from ..runs.client import check_reachable, client_for, experiment_id, mark_training_experiment
from ..runs.views import SHARED_VIEW_TAG, VIEW_KEY, headline_view, runs_table_fragment, runs_table_url, saved_view
from .uiapp import APP_NAME, EXPERIMENT_ENV, LANDING_ENV

JOB_EXECUTION_ENV = "MLFLOW_SERVER_ENABLE_JOB_EXECUTION"
# MLflow's documented switch of its AI Gateway "endpoints and UI" (environment_variables.py; the server reports it
# as server-info's features_enabled.gateway): off, the UI's GenAI entry points that hang on it (AI Gateway,
# Judges, Playground) are not shown. The experiment's and run's "Traces" tabs have no such switch (docs/training.md).
GATEWAY_ENV = "MLFLOW_ENABLE_AI_GATEWAY"
STORE_ENV = "MLFLOW_BACKEND_STORE_URI"  # `mlflow ui --backend-store-uri` read from the environment


def default_workers(cores: int | None = None) -> int:
    """Server worker processes: half the cores, at least 1 and at most 4 (one person browsing needs few)."""
    cores = cores if cores is not None else (os.cpu_count() or 1)
    return max(1, min(4, cores // 2))


def app_registered() -> bool:
    """Whether MLflow finds our app, ``uiapp`` (the ``mlflow.app`` entry point ``bronchopose``, pyproject.toml):
    an install of bronchocli older than it has none."""
    return any(ep.name == APP_NAME for ep in importlib.metadata.entry_points(group="mlflow.app"))


EVERY_INTERFACE = ("0.0.0.0", "::")
ALLOWED_NAME = re.compile(r"[A-Za-z0-9_*][A-Za-z0-9_.*-]*|\[[0-9A-Fa-f:.]+\]")  # a --allowed-host value


def _names_of_this_machine(host: str) -> set[str]:
    """The names and addresses a browser elsewhere reaches this machine by: its hostname and FQDN, ``host`` when
    it names one interface, and the addresses they resolve to."""
    names = {socket.gethostname(), socket.getfqdn()}
    if host not in EVERY_INTERFACE:
        names.add(host)
    for name in list(names):
        try:
            names |= {info[4][0] for info in socket.getaddrinfo(name, None, type=socket.SOCK_STREAM)}
        except OSError:
            continue
    return {n for n in names if n}


def allowed_hosts(host: str, port: int, extra: Sequence[str] = ()) -> list[str]:
    """The Host headers the server answers with ``--expose``: MLflow's defaults (loopback, private addresses),
    this machine's names and addresses and the ``extra`` names (``--allowed-host``: a DNS alias, a reverse
    proxy's name), bare and with the port (an IPv6 address in brackets). Without it MLflow answers a request
    naming the machine's hostname with 403 "Invalid Host header" (DNS-rebinding protection)."""
    from mlflow.server.security_utils import get_default_allowed_hosts  # lazy: mlflow.server loads Flask; --expose only

    out = list(get_default_allowed_hosts())
    names = sorted(_names_of_this_machine(host)) if host else []
    for name in [*names, *(n for n in dict.fromkeys(extra) if n not in names)]:
        shown = f"[{name}]" if ":" in name else name
        out += [shown, f"{shown}:{port}"]
    return out


def link_host(host: str) -> str:
    """The host of the printed link: the machine's hostname when listening on every interface (0.0.0.0 is no
    address a browser can open), else ``host`` (an IPv6 literal in brackets)."""
    if host in EVERY_INTERFACE:
        return socket.gethostname()
    return f"[{host}]" if ":" in host else host


def ui_command(cfg: Config, host: str, port: int, workers: int | None = None, app: bool = True,
               expose: bool = False, allowed: Sequence[str] = ()) -> list[str]:
    """The `mlflow ui` argv serving the config's artifact root with ``workers`` processes, through the front
    page's app (``uiapp``) when ``app``; with ``expose``, answering requests that name this machine, and with
    ``allowed`` (``--allowed-host``) the names given too (``allowed_hosts``).

    The store's URI is not on it (a process's argv is public in ``ps``; the URI may hold a password): it goes
    through the environment (``server_env``, ``MLFLOW_BACKEND_STORE_URI``, which `mlflow ui` reads)."""
    exe = str(Path(sys.executable).with_name("mlflow"))
    if not Path(exe).exists():
        exe = shutil.which("mlflow") or exe
    argv = [exe, "ui", "--host", host, "--port", str(port),
            "--workers", str(workers or default_workers())]
    if app:
        argv += ["--app-name", APP_NAME]
    if expose or allowed:
        argv += ["--allowed-hosts", ",".join(allowed_hosts(host if expose else "", port, allowed))]
    if not urls.is_server(cfg.paths.mlflow_uri):
        argv += ["--default-artifact-root", cfg.paths.artifacts.as_uri()]
    return argv


def server_env(environ: dict[str, str] | None = None, store_uri: str | None = None, landing: str | None = None,
               experiment: str | None = None) -> dict[str, str]:
    """The server's environment: the store's URI (``store_uri``: never on the command line), the GenAI job
    runner and the AI Gateway (its endpoints and UI entry points) off unless the user asked for them, the page's landing (``landing``: a UI route) and the experiment whose
    table opens on the headline view (``experiment``, ``uiapp``)."""
    env = dict(os.environ if environ is None else environ)
    env.setdefault(JOB_EXECUTION_ENV, "false")
    env.setdefault(GATEWAY_ENV, "false")  # a training experiment has no LLM endpoints; the user's choice wins
    if store_uri is not None:
        env[STORE_ENV] = store_uri
    if landing is not None:
        env[LANDING_ENV] = landing
    if experiment is not None:
        env[EXPERIMENT_ENV] = experiment
    return env


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


def is_loopback(host: str) -> bool | None:
    """Whether every address ``host`` names is a loopback one (127.0.0.0/8, ::1); None: not a name of any address
    (``check_port`` words that). ``0.0.0.0`` and ``::`` (every interface) are not loopback."""
    try:
        found = {info[4][0] for info in socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)}
    except (socket.gaierror, UnicodeError):
        return None
    return bool(found) and all(ipaddress.ip_address(a.partition("%")[0]).is_loopback for a in found)


def check_host(host: str, expose: bool, warn: Callable[[str], None]) -> None:
    """The UI listens on loopback unless ``expose``: MLflow's UI has no authentication, so any other interface
    lets whoever reaches it read, change and delete every run. BronchoError without ``expose``; a warning with it."""
    if is_loopback(host) is not False:
        return
    risk = (f"MLflow's UI has no authentication: anyone who can reach {host}:<port> can read, change and delete "
            "every experiment, run and artifact of this store")
    if not expose:
        raise BronchoError(f"--host {host}: not a loopback address; {risk}. Keep the default 127.0.0.1 (reach it "
                           "from elsewhere through `ssh -L`), or add --expose to listen there anyway, behind "
                           "authentication (docs/training.md, \"Serving the UI to others\")")
    warn(f"warning: --expose: listening on {host}; {risk}. Put it behind authentication (MLflow's basic-auth app "
         "or a reverse proxy: docs/training.md, \"Serving the UI to others\")")


def check_names(names: Sequence[str]) -> list[str]:
    """``--allowed-host`` values: host names or addresses, no scheme, path, port or comma (BronchoError naming it)."""
    for name in names:
        if not name or not ALLOWED_NAME.fullmatch(name):
            raise BronchoError(f"--allowed-host {name!r}: not a host name or address (allowed: letters, digits, "
                               "'.', '-', '_', an IPv6 address in brackets, '*' as a wildcard, e.g. review.example)")
    return list(names)


def serve(cfg: Config, host: str, port: int, workers: int | None, console: Console, *, expose: bool = False,
          warn: Callable[[str], None] | None = None, allowed: Sequence[str] = ()) -> None:
    """Check the host (``check_host``), the store and the port, print the runs-table link and become `mlflow ui`
    (never returns)."""
    allowed = check_names(allowed)
    check_host(host, expose, warn or (lambda line: print(line, file=sys.stderr, flush=True)))
    if urls.is_server(cfg.paths.mlflow_uri):
        raise BronchoError(f"runs.uri {urls.redact(cfg.paths.mlflow_uri)} is already a server: open it in a browser")
    check_port(host, port)
    check_reachable(cfg)  # `mlflow ui` itself would retry a dead database for minutes
    app = app_registered()
    argv = ui_command(cfg, host, port, workers, app=app, expose=expose, allowed=allowed)
    if not Path(argv[0]).exists():
        raise BronchoError("the `mlflow` executable was not found next to this Python; reinstall bronchocli")
    cfg.paths.artifacts.mkdir(parents=True, exist_ok=True)
    client = client_for(cfg)
    exp_id = experiment_id(client, cfg)  # created now if no run exists yet: the link works at once
    mark_training_experiment(client, exp_id)
    client.set_experiment_tag(exp_id, SHARED_VIEW_TAG + VIEW_KEY, saved_view(headline_view(), int(time.time() * 1000)))
    base = f"http://{link_host(host)}:{port}"
    if not app:
        (warn or (lambda line: print(line, file=sys.stderr, flush=True)))(
            f"warning: MLflow does not know the app {APP_NAME!r} (bronchocli installed before it existed): the UI's "
            "own navigation lands on MLflow's GenAI overview; reinstall bronchocli (pip install -e .) or use the "
            "link below")
    console.print(f"MLflow UI for {urls.redact(cfg.paths.mlflow_uri)} at {base} (Ctrl-C to stop)\n"
                  f"runs of experiment {cfg.experiment_name}: {runs_table_url(base, exp_id)}",
                  highlight=False, soft_wrap=True)
    sys.stdout.flush()
    os.execve(argv[0], argv, server_env(store_uri=cfg.paths.mlflow_uri, landing=runs_table_fragment(exp_id),
                                           experiment=exp_id))
