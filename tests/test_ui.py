"""`bronchopose ui` really serves the configured MLflow store on 127.0.0.1."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass(frozen=True)
class Served:
    folder: Path  # where `bronchopose ui` ran (its experiments.yaml, runs/)
    port: int
    log: Path  # the process's stdout and stderr


@pytest.fixture(scope="module")
def default_ui(tmp_path_factory):
    """One default `bronchopose ui` process (no --workers, no --host) on a config's store, up and answering
    /health, shared by the tests that read it: booting MLflow's server is most of their time."""
    folder = tmp_path_factory.mktemp("ui")
    (folder / "experiments.yaml").write_text("name: ui-test\n")
    port, log = free_port(), folder / "ui.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-c", MAIN, "ui", "--port", str(port)], cwd=folder, stdout=out,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True,
                                env={**os.environ, "COLUMNS": "200"})
    try:
        deadline = time.monotonic() + 300  # a guard, not a timing claim: a starved shared CPU takes minutes
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2) as response:
                    assert response.status == 200 and response.read().strip() == b"OK"
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"the UI did not come up:\n{log.read_text()}")
                time.sleep(0.2)
        yield Served(folder, port, log)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=30)


def test_ui_serves_the_store(default_ui):
    port = default_ui.port
    assert (default_ui.folder / "runs" / "mlflow.db").is_file()  # it serves the config's store
    # the printed link is the experiment's runs table in the model-training view, for the id the server has
    query = urllib.parse.urlencode({"experiment_name": "ui-test"})
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/2.0/mlflow/experiments/get-by-name?{query}",
                                timeout=10) as response:
        experiment = json.load(response)["experiment"]
    link = (f"http://127.0.0.1:{port}/#/experiments/{experiment['experiment_id']}/runs?workflowType=machine_learning"
            "&viewStateShareKey=bronchopose-headline")
    tags = {t["key"]: t["value"] for t in experiment["tags"]}
    assert tags["mlflow.experimentKind"] == "custom_model_development"
    saved = json.loads(tags["mlflow.sharedViewState.bronchopose-headline"])  # MLflow's saved-view envelope
    assert saved["name"] and isinstance(saved["createdAt"], int)  # listed by name in the Views menu
    assert json.loads(saved["state"])["orderByAsc"] is True  # the view
    # MLflow's page with our script (issues 36.5, 48.5): model-training mode, the runs table on the view
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as response:
        page = response.read().decode()
    assert "mlflow.workflowType_v1" in page and link.split("/", 3)[3].lstrip("/") in page.replace("\\/", "/")
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/?ui=bronchopose", timeout=10) as response:
        assert "static-files" in response.read().decode()  # MLflow's own UI behind it
    # printed (and flushed) before the process becomes MLflow's server
    assert f"runs of experiment ui-test: {link}" in default_ui.log.read_text()


def test_ui_refuses_a_remote_tracking_server(tmp_path, cli):
    (tmp_path / "experiments.yaml").write_text("name: t\nruns: {uri: 'http://mlflow.example:5000'}\n")
    code, _, err = cli("ui", "-c", str(tmp_path / "experiments.yaml"))
    assert code == 2 and "already a server" in err


def test_the_server_is_sized_for_the_machine(tmp_path, monkeypatch):
    from bronchocli.config import Config
    from bronchocli.runs import ui

    assert [ui.default_workers(n) for n in (1, 2, 3, 8, 64)] == [1, 1, 1, 4, 4]  # not 4 workers on 2 cores
    cfg = Config(name="t").with_values({"runs.uri": f"sqlite:///{tmp_path / 'm.db'}"})
    argv = ui.ui_command(cfg, "127.0.0.1", 5000, workers=3)
    assert argv[argv.index("--workers") + 1] == "3" and argv[1] == "ui"
    assert argv[argv.index("--app-name") + 1] == "bronchopose" and ui.app_registered()  # our app
    assert "--app-name" not in ui.ui_command(cfg, "127.0.0.1", 5000, workers=3, app=False)  # an older install
    monkeypatch.delenv(ui.JOB_EXECUTION_ENV, raising=False)
    assert ui.server_env()[ui.JOB_EXECUTION_ENV] == "false"  # no GenAI task consumers for a training experiment
    assert ui.server_env({ui.JOB_EXECUTION_ENV: "true"})[ui.JOB_EXECUTION_ENV] == "true"  # the user's choice wins


def test_the_server_runs_without_mlflows_ai_gateway_unless_asked(monkeypatch):
    """Issue 57.5: MLflow's documented switch of its AI Gateway (endpoints and UI entry points) is off for the UI
    server; MLflow reads it under that name (a rename in a new MLflow fails here), a user's value wins."""
    from mlflow.environment_variables import MLFLOW_ENABLE_AI_GATEWAY

    from bronchocli.runs import ui

    monkeypatch.delenv(ui.GATEWAY_ENV, raising=False)
    env = ui.server_env()
    assert env[ui.GATEWAY_ENV] == "false" and MLFLOW_ENABLE_AI_GATEWAY.name == ui.GATEWAY_ENV
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    assert MLFLOW_ENABLE_AI_GATEWAY.get() is False  # what MLflow's server-info reports as features_enabled.gateway
    assert ui.server_env({ui.GATEWAY_ENV: "true"})[ui.GATEWAY_ENV] == "true"


def test_the_store_uri_goes_to_the_server_through_its_environment_never_its_argv():
    from bronchocli.config import Config
    from bronchocli.runs import ui

    uri = "postgresql://bp:hunter22@db.example/mlflow?password=hunter23"
    cfg = Config(name="t").with_values({"runs.uri": uri})
    argv = ui.ui_command(cfg, "127.0.0.1", 5000, workers=1)
    assert "hunter2" not in " ".join(argv) and "--backend-store-uri" not in argv  # `ps` shows argv to everyone
    assert ui.server_env({}, store_uri=cfg.paths.mlflow_uri)[ui.STORE_ENV] == uri  # what `mlflow ui` reads


def test_mlflows_page_gets_our_script_first_whatever_its_query_and_the_rest_is_mlflows():
    """Issues 36.5, 48.5: every load of MLflow's page (``/``, ``/?ui=bronchopose``, any address copied from the bar)
    runs our script before MLflow's; it stores MLflow's settings only where the browser has none, and lands an
    address without a fragment on the runs table. Other requests are MLflow's, untouched."""
    import asyncio

    from bronchocli.runs import uiapp

    mlflow_page = b'<!doctype html><html lang="en"><head><meta charset="utf-8"/><script src="main.js"></script></head>'
    asked: list[dict] = []

    async def fake_mlflow(scope, receive, send):  # MLflow's app: its page at /, JSON elsewhere
        asked.append(scope)
        html = scope["path"] == "/"
        body = mlflow_page if html else b'{"runs": []}'
        await send({"type": "http.response.start", "status": 200, "headers": [
            (b"content-type", b"text/html; charset=utf-8" if html else b"application/json"),
            (b"content-length", str(len(body)).encode()), (b"etag", b"x")]})
        await send({"type": "http.response.body", "body": body[:20], "more_body": True})
        await send({"type": "http.response.body", "body": body[20:]})

    async def call(method: str, path: str, query: bytes) -> list[dict]:
        sent: list[dict] = []

        async def send(message):
            sent.append(message)

        scope = {"type": "http", "method": method, "path": path, "query_string": query,
                 "headers": [(b"accept-encoding", b"gzip"), (b"if-none-match", b"x"), (b"host", b"h")]}
        await uiapp.app(scope, None, send)
        return sent

    previous = uiapp._mlflow_app
    uiapp._mlflow_app = fake_mlflow
    os.environ[uiapp.LANDING_ENV] = "#/experiments/7/runs?viewStateShareKey=k"
    os.environ[uiapp.EXPERIMENT_ENV] = "7"
    try:
        for query in (b"", b"ui=bronchopose", b"o=1"):
            start, *bodies = asyncio.run(call("GET", "/", query))
            page = b"".join(m.get("body", b"") for m in bodies).decode()
            assert start["status"] == 200 and dict(start["headers"])[b"content-length"] == str(len(page)).encode()
            assert (b"cache-control", b"no-store") in start["headers"] and b"etag" not in dict(start["headers"])
            head = page.split("<head>", 1)[1]
            assert head.startswith("<script>") and head.index("main.js") > head.index("mlflow.workflowType_v1")
            assert "#/experiments/7/runs?viewStateShareKey=k" in page and "replaceState" in page
            assert 'MLflowLocalStorage-1.1-ExperimentPage-[\\"7\\"]-ReactComponentState' in page
        assert {k for k, _ in asked[0]["headers"]} == {b"host"}  # the page asked for whole and plain
        start, body = asyncio.run(call("HEAD", "/", b""))
        assert body["body"] == b"" and int(dict(start["headers"])[b"content-length"]) > len(mlflow_page)
        start, *bodies = asyncio.run(call("GET", "/ajax-api/2.0/mlflow/runs/search", b""))
        assert b"".join(m.get("body", b"") for m in bodies) == b'{"runs": []}'  # MLflow's, as it answered
        assert (b"etag", b"x") in start["headers"]
    finally:
        uiapp._mlflow_app = previous
        del os.environ[uiapp.LANDING_ENV], os.environ[uiapp.EXPERIMENT_ENV]
    script = uiapp.page_script("</script><b>x", None)
    assert script.count("</script>") == 1 and "<b>x" in script  # a landing cannot end the script early
    assert "ExperimentPage" not in script  # no experiment: no table state stored
    assert uiapp.with_script(b"<p>no head</p>", script) == b"<p>no head</p>"


def test_the_page_script_stores_mlflows_settings_only_where_the_browser_has_none():
    """The script run in a JavaScript engine when one is installed (node): a fresh browser gets the mode, the
    experiment's headline view, the Assistant closed and a run's curves first; a browser with its own values keeps
    them; other keys read as they are."""
    import shutil

    from bronchocli.runs import uiapp
    from bronchocli.runs.views import CURVE_METRICS, headline_view

    node = shutil.which("node") or shutil.which("nodejs")
    if node is None:
        pytest.skip("no JavaScript engine (node); the browser tests run the script in Chromium")
    script = uiapp.page_script("#/experiments/7/runs", "7").removeprefix("<script>").removesuffix("</script>")
    harness = """
    function Storage() { this.data = {}; }
    Storage.prototype.getItem = function (k) { return k in this.data ? this.data[k] : null; };
    Storage.prototype.setItem = function (k, v) { this.data[k] = String(v); };
    var store = new Storage(), replaced = [];
    store.data = JSON.parse(process.argv[1]);
    global.Storage = Storage;
    global.window = {localStorage: store, location: {hash: process.argv[2], pathname: "/", search: "?ui=b"},
                     history: {replaceState: function (a, b, url) { replaced.push(url); }}};
    SCRIPT
    var run = "MLflowLocalStorage-1.1-RunPage-0123abcd-model-chartUIState";
    var other = "MLflowLocalStorage-1.1-RunPage-0123abcd-system-chartUIState";
    console.log(JSON.stringify({first: store.getItem(run), other: store.getItem(other), data: store.data,
                                replaced: replaced}));
    """.replace("SCRIPT", script)
    run = "MLflowLocalStorage-1.1-RunPage-0123abcd-model-chartUIState"

    def page(stored: dict, hash_: str) -> dict:
        done = subprocess.run([node, "-e", harness, json.dumps(stored), hash_], capture_output=True, text=True,
                              timeout=60)
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    fresh = page({}, "")
    assert fresh["replaced"] == ["/?ui=b#/experiments/7/runs"]  # no fragment: the landing
    assert fresh["data"]["mlflow.workflowType_v1"] == '"machine_learning"'
    assert fresh["data"]["mlflow.assistant.panelOpen_v1"] == "false"
    assert fresh["data"]["mlflow.assistant.fab.autoOpenedOnFirstLoad_v1"] == "true"  # MLflow opens it once else
    assert json.loads(fresh["data"][uiapp.experiment_state_key("7")]) == headline_view()
    layout = json.loads(fresh["first"])
    assert [c["metricKey"] for c in layout["compareRunCharts"]] == list(CURVE_METRICS)
    assert fresh["data"][run] == fresh["first"] and fresh["other"] is None  # stored; the system tab untouched
    mine = {"mlflow.workflowType_v1": '"genai"', "mlflow.assistant.panelOpen_v1": "true",
            "mlflow.assistant.fab.autoOpenedOnFirstLoad_v1": "false",
            uiapp.experiment_state_key("7"): "{}", run: '{"mine": 1}'}
    kept = page(mine, "#/experiments")
    assert kept["replaced"] == [] and kept["data"] == mine and kept["first"] == '{"mine": 1}'


# -- issue 37.6: loopback unless asked, with a warning naming the risk ---------------------------------------------

def _listening(port: int) -> set[str]:
    """The local addresses listening on TCP ``port`` (``/proc/net/tcp`` and ``tcp6``), e.g. {"127.0.0.1"}."""
    import ipaddress

    found = set()
    for name, size in (("tcp", 4), ("tcp6", 16)):
        path = f"/proc/net/{name}"
        if not os.path.exists(path):
            continue
        with open(path) as f:
            for line in f.readlines()[1:]:
                local, state = line.split()[1], line.split()[3]
                address, _, hexport = local.partition(":")
                if state != "0A" or int(hexport, 16) != port:  # 0A: LISTEN
                    continue
                raw = bytes.fromhex(address)
                raw = b"".join(raw[i:i + 4][::-1] for i in range(0, size, 4))  # each 32-bit word little-endian
                found.add(str(ipaddress.ip_address(raw)))
    return found


@pytest.fixture
def exec_argv(monkeypatch):
    """What `bronchopose ui` would become: the argv it hands to os.execve (nothing is started)."""
    from bronchocli.runs import ui

    seen: list[list[str]] = []

    def fake_exec(path, argv, env):
        seen.append(list(argv))
        raise SystemExit(0)

    monkeypatch.setattr(ui.os, "execve", fake_exec)
    return seen


def test_the_ui_listens_on_loopback_by_default(tmp_path, cli, exec_argv):
    (tmp_path / "experiments.yaml").write_text("name: t\n")
    code, out, err = cli("ui", "-c", str(tmp_path / "experiments.yaml"), "--port", str(free_port()))
    assert code == 0 and not err.strip(), err
    (argv,) = exec_argv
    assert argv[argv.index("--host") + 1] == "127.0.0.1"


def test_the_real_server_listens_on_loopback_only(default_ui):
    """The default `bronchopose ui` process: its socket is bound to 127.0.0.1, not to every interface."""
    if not os.path.exists("/proc/net/tcp"):
        pytest.skip("no /proc/net/tcp on this system")
    assert _listening(default_ui.port) == {"127.0.0.1"}


@pytest.mark.parametrize("host", ["0.0.0.0", "::"])
def test_another_host_without_expose_is_one_line_and_exit_2(tmp_path, cli, exec_argv, host):
    (tmp_path / "experiments.yaml").write_text("name: t\n")
    code, out, err = cli("ui", "-c", str(tmp_path / "experiments.yaml"), "--host", host, "--port", str(free_port()))
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and not exec_argv, err
    assert lines[0].startswith(f"error: --host {host}: not a loopback address") and "--expose" in lines[0]
    assert "no authentication" in lines[0]
    assert not (tmp_path / "runs").exists()  # refused before the store is touched


def test_expose_listens_there_and_warns_naming_the_risk(tmp_path, cli, exec_argv):
    (tmp_path / "experiments.yaml").write_text("name: t\n")
    code, out, err = cli("ui", "-c", str(tmp_path / "experiments.yaml"), "--host", "0.0.0.0", "--expose",
                         "--port", str(free_port()))
    assert code == 0, err
    (argv,) = exec_argv
    assert argv[argv.index("--host") + 1] == "0.0.0.0"
    (warning,) = [line for line in err.splitlines() if line.strip()]
    assert warning.startswith("warning: --expose: listening on 0.0.0.0") and "no authentication" in warning
    assert "basic-auth" in warning and "reverse proxy" in warning
    # MLflow answers requests naming this machine (not only loopback), and the link names the machine
    port = int(argv[argv.index("--port") + 1])
    allowed = argv[argv.index("--allowed-hosts") + 1].split(",")
    assert {socket.gethostname(), f"{socket.gethostname()}:{port}", "localhost:*"} <= set(allowed)
    assert f"http://{socket.gethostname()}:{port}/#/experiments/" in out and "0.0.0.0" not in out


def test_with_expose_a_request_naming_this_machine_reads_a_run_through_the_api(tmp_path):
    """MLflow refuses a Host header it does not know (DNS-rebinding protection: 403 "Invalid Host header"), which
    every browser on another machine sends; with --expose the server answers the machine's names. Tested on
    loopback only: the server listens on 127.0.0.1 and the request goes there, naming the machine's hostname."""
    (tmp_path / "experiments.yaml").write_text("name: expose-test\n")
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-c", MAIN, "ui", "--port", str(port), "--workers", "1", "--expose"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)

    def get(path: str, host: str) -> tuple[int, bytes]:
        request = urllib.request.Request(f"http://127.0.0.1:{port}{path}", headers={"Host": host})
        try:
            with urllib.request.urlopen(request, timeout=10) as response:
                return response.status, response.read()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read()

    try:
        deadline = time.monotonic() + 300  # a guard, not a timing claim: a starved shared CPU takes minutes
        while True:
            try:
                if get("/health", f"127.0.0.1:{port}")[0] == 200:
                    break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"the UI did not come up:\n{proc.stdout.read() if proc.poll() is not None else ''}")
            time.sleep(0.2)
        query = urllib.parse.urlencode({"experiment_name": "expose-test"})
        status, body = get(f"/api/2.0/mlflow/experiments/get-by-name?{query}", f"{socket.gethostname()}:{port}")
        assert status == 200, body[:200]
        experiment_id = json.loads(body)["experiment"]["experiment_id"]
        request = urllib.request.Request(f"http://127.0.0.1:{port}/api/2.0/mlflow/runs/create", method="POST",
                                         data=json.dumps({"experiment_id": experiment_id}).encode(),
                                         headers={"Host": f"{socket.gethostname()}:{port}",
                                                  "Content-Type": "application/json"})
        with urllib.request.urlopen(request, timeout=10) as response:
            run_id = json.load(response)["run"]["info"]["run_id"]
        status, body = get(f"/api/2.0/mlflow/runs/get?run_id={run_id}", f"{socket.gethostname()}:{port}")
        assert status == 200 and json.loads(body)["run"]["info"]["run_id"] == run_id
        assert get(f"/api/2.0/mlflow/runs/get?run_id={run_id}", f"rebind.invalid:{port}")[0] == 403  # still guarded
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)


def test_allowed_host_is_answered_and_another_name_is_told_what_to_pass(tmp_path):
    """Issue 57, item 6: `ui --expose --allowed-host review.example` answers ``Host: review.example`` (a DNS alias,
    a reverse proxy) with 200, on loopback; a name it was not given gets 403 naming the flag to pass."""
    (tmp_path / "experiments.yaml").write_text("name: alias-test\n")
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-c", MAIN, "ui", "--port", str(port), "--workers", "1", "--expose",
                             "--allowed-host", "review.example"], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)

    def get(path: str, host: str) -> tuple[int, bytes]:
        request = urllib.request.Request(f"http://127.0.0.1:{port}{path}", headers={"Host": host})
        try:
            with urllib.request.urlopen(request, timeout=10) as response:
                return response.status, response.read()
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read()

    try:
        deadline = time.monotonic() + 300  # a guard, not a timing claim: a starved shared CPU takes minutes
        while True:
            try:
                if get("/health", f"127.0.0.1:{port}")[0] == 200:
                    break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"the UI did not come up:\n{proc.stdout.read() if proc.poll() is not None else ''}")
            time.sleep(0.2)
        query = urllib.parse.urlencode({"experiment_name": "alias-test"})
        for host in ("review.example", f"review.example:{port}"):
            status, body = get(f"/api/2.0/mlflow/experiments/get-by-name?{query}", host)
            assert status == 200 and json.loads(body)["experiment"]["name"] == "alias-test", body[:200]
        status, body = get(f"/api/2.0/mlflow/experiments/get-by-name?{query}", f"other.example:{port}")
        assert status == 403 and "--allowed-host other.example" in body.decode(), body[:300]
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)


@pytest.mark.parametrize("host, loopback", [("127.0.0.1", True), ("127.0.0.2", True), ("localhost", True),
                                            ("::1", True), ("0.0.0.0", False), ("::", False),
                                            ("no-such-host.invalid", None)])
def test_what_counts_as_loopback(host, loopback):
    from bronchocli.runs.ui import is_loopback

    assert is_loopback(host) is loopback
