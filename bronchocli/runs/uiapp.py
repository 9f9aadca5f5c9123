"""The server app `bronchopose ui` runs: MLflow's own app, its page given a few first settings (issues 36.5, 48.5).

MLflow 3.17's UI keeps its choices in the browser's ``localStorage`` and reads
nothing of them from the server:

* its mode (GenAI or model training) comes from the URL's ``workflowType`` or
  else ``localStorage["mlflow.workflowType_v1"]`` (default GenAI), which only
  its sidebar's switch writes; the experiment tag ``mlflow.experimentKind`` is
  not read for it. A fresh browser that opens any address of the UI and then
  Experiments, then the experiment, lands on the GenAI overview;
* an experiment's runs table opens on the state saved for it
  (``MLflowLocalStorage-1.1-ExperimentPage-["<id>"]-ReactComponentState``:
  the search facets and table state a saved view holds), MLflow's default
  (newest first, every column) when there is none;
* a run's "Model metrics" charts open on the layout saved for that run
  (``MLflowLocalStorage-1.1-RunPage-<run id>-model-chartUIState``), or, when
  there is none, on one chart per metric sorted by name in one "Model metrics"
  section (a metric named ``prefix/name`` gets a section ``prefix``, sorted
  before it): the training curves among ~160 one-value test metrics;
* its Assistant panel is open when ``mlflow.assistant.panelOpen_v1`` says so,
  and MLflow opens it by itself on a local server's first load (then sets
  ``mlflow.assistant.fab.autoOpenedOnFirstLoad_v1``).

This app is MLflow's (``mlflow.server.fastapi_app:app``, unchanged) with a
small script of ours put first in the ``<head>`` of the page MLflow serves at
``/`` (whatever the query: ``/``, ``/?ui=bronchopose`` and every address
copied from the bar are that page with a fragment). Before MLflow's own
script runs it stores, only where the browser has no value yet (a choice the
user made is kept):

* ``"machine_learning"`` as the mode (what one click on "Model training"
  stores), so MLflow's own navigation opens runs tables, not the GenAI overview;
* the headline view (``views.headline_view``) as the saved state of the
  configured experiment's runs table, so Experiments, then the experiment, opens
  on it;
* the panel closed, and its first-load opening as done;
* the run page's layout (``views.run_page_layout``: the training and validation
  curves first) as a run's saved chart layout at the moment MLflow's run page
  looks for one and finds none (any run, however the page was reached);

and an address without a fragment (the UI's bare address) gets the
experiment's runs table on the headline view (``LANDING_ENV``). Every other
request (its files, the REST API) goes to MLflow's app as it is. MLflow loads
it through its documented app plugin mechanism (the ``mlflow.app`` entry point
``bronchopose``, as its ``basic-auth`` app is: ``mlflow ui --app-name
bronchopose``); nothing in MLflow's files is changed.
``tests/training/test_ui_browser.py`` asserts all this in a real browser, so an
MLflow release that renames a key fails there.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any

from .views import headline_view, run_page_layout

APP_NAME = "bronchopose"  # the mlflow.app entry point (pyproject.toml)
LANDING_ENV = "BRONCHOPOSE_UI_LANDING"  # the fragment to land on when the page is opened without one
EXPERIMENT_ENV = "BRONCHOPOSE_UI_EXPERIMENT"  # the experiment whose runs table opens on the headline view
WORKFLOW_KEY = "mlflow.workflowType_v1"  # MLflow 3.17's localStorage key of the GenAI / Model training switch
MODEL_TRAINING = "machine_learning"
ASSISTANT_KEY = "mlflow.assistant.panelOpen_v1"  # MLflow 3.17's Assistant panel, open or closed
# set once MLflow 3.17 has opened its Assistant panel by itself (on a local server's first load: the panel then
# takes ~30 % of the width); stored as done, it leaves the panel closed until the user opens it
ASSISTANT_OPENED_KEY = "mlflow.assistant.fab.autoOpenedOnFirstLoad_v1"
STORE_PREFIX = "MLflowLocalStorage-1.1-"  # MLflow 3.17's LocalStorageUtils: <prefix><component>-<id>-<item>
RUN_LAYOUT_KEY = re.compile(r"^MLflowLocalStorage-1\.1-RunPage-[0-9a-zA-Z]+-model-chartUIState$")
_DROPPED = {b"if-none-match", b"if-modified-since", b"accept-encoding"}  # the page itself, whole and plain

_mlflow_app: Any = None


def experiment_state_key(experiment_id: str) -> str:
    """The localStorage key of MLflow 3.17's saved runs-table state for one experiment."""
    return f"{STORE_PREFIX}ExperimentPage-{json.dumps([str(experiment_id)])}-ReactComponentState"


def page_script(landing: str | None, experiment_id: str | None) -> str:
    """The script put first in MLflow's page: MLflow's settings stored where the browser has none (the mode, the
    experiment's runs table on the headline view, the Assistant closed, a run's charts on its curves), and
    ``landing`` as the fragment of an address that has none."""
    seeds = {WORKFLOW_KEY: json.dumps(MODEL_TRAINING), ASSISTANT_KEY: json.dumps(False),
             ASSISTANT_OPENED_KEY: json.dumps(True)}
    if experiment_id:
        seeds[experiment_state_key(experiment_id)] = json.dumps(headline_view())
    script = (
        "(function () {"
        f"var seeds = {json.dumps(seeds)}, layout = {json.dumps(json.dumps(run_page_layout()))};"
        f"var runLayout = new RegExp({json.dumps(RUN_LAYOUT_KEY.pattern)});"
        "try {"
        " var store = window.localStorage, getItem = Storage.prototype.getItem;"
        " Object.keys(seeds).forEach(function (k) {"
        "  if (getItem.call(store, k) === null) store.setItem(k, seeds[k]); });"
        # MLflow's run page reads its saved layout once, when the page of a run opens: where it finds none, it
        # finds ours (stored, so it is the run's saved layout from then on, which MLflow and the user update)
        " Storage.prototype.getItem = function (key) {"
        "  var value = getItem.call(this, key);"
        "  if (value === null && this === store && runLayout.test(String(key))) {"
        "   this.setItem(key, layout); value = layout; }"
        "  return value; };"
        "} catch (e) {}"
        f"var landing = {json.dumps(landing or '')};"
        "if (landing && (!window.location.hash || window.location.hash === '#'))"
        " window.history.replaceState(null, '', window.location.pathname + window.location.search + landing);"
        "})();"
    ).replace("</", "<\\/")
    return f"<script>{script}</script>"


def with_script(page: bytes, script: str) -> bytes:
    """MLflow's page with ``script`` first in its ``<head>`` (before MLflow's own scripts); the page unchanged when
    it has no ``<head>`` (not MLflow's page)."""
    match = re.search(rb"<head[^>]*>", page, re.IGNORECASE)
    if match is None:
        return page
    return page[:match.end()] + script.encode() + page[match.end():]


def _mlflow() -> Any:
    global _mlflow_app
    if _mlflow_app is None:
        from mlflow.server.fastapi_app import app as mlflow_app  # lazy: builds MLflow's whole server app

        _mlflow_app = mlflow_app
    return _mlflow_app


async def _page(scope: dict, receive: Any, send: Any) -> None:
    """MLflow's page at ``/``, asked for whole and uncompressed, sent on with our script in its head."""
    method = scope["method"]
    scope = {**scope, "method": "GET",
             "headers": [(k, v) for k, v in scope.get("headers", []) if k.lower() not in _DROPPED]}
    start: dict = {}
    body = bytearray()

    async def collect(message: dict) -> None:
        if message["type"] == "http.response.start":
            start.update(message)
        elif message["type"] == "http.response.body":
            body.extend(message.get("body", b""))

    await _mlflow()(scope, receive, collect)
    headers = [(k, v) for k, v in start.get("headers", []) if k.lower() not in (b"content-length", b"etag",
                                                                                  b"last-modified", b"cache-control")]
    page = bytes(body)
    if start.get("status") == 200 and any(k.lower() == b"content-type" and v.startswith(b"text/html")
                                          for k, v in headers):
        page = with_script(page, page_script(os.environ.get(LANDING_ENV), os.environ.get(EXPERIMENT_ENV)))
    headers += [(b"content-length", str(len(page)).encode()), (b"cache-control", b"no-store")]
    await send({"type": "http.response.start", "status": start.get("status", 500), "headers": headers})
    await send({"type": "http.response.body", "body": b"" if method == "HEAD" else page})


def refused_host_text(host_header: str) -> str:
    """The body of MLflow's 403 for a Host header it does not answer, saying what to pass (issue 57, item 6)."""
    name = host_header.rsplit(":", 1)[0] if host_header.count(":") == 1 else host_header
    name = name or "<name>"
    return (f"Invalid Host header {host_header!r}: this server does not answer requests naming {name} (MLflow's "
            f"DNS-rebinding protection). If {name} is this machine's name (a DNS alias, a reverse proxy), start the "
            f"UI with: bronchopose ui --expose --allowed-host {name} (repeatable; see docs/training.md)\n")


async def with_host_hint(inner: Any, scope: dict, receive: Any, send: Any) -> None:
    """``inner``'s answer, its 403 "Invalid Host header" (MLflow's plain text) replaced by ``refused_host_text``."""
    from mlflow.server.security_utils import INVALID_HOST_MSG  # lazy: the app is built by then anyway

    held: dict = {}

    async def relay(message: dict) -> None:
        if message["type"] == "http.response.start" and message.get("status") == 403:
            held.update(start=message, body=b"")  # hold it to its last chunk: only MLflow's host refusal is rewritten
            return
        if message["type"] != "http.response.body" or "start" not in held:
            await send(message)
            return
        held["body"] += message.get("body", b"")
        if message.get("more_body"):
            return
        start, body = held.pop("start"), held.pop("body")
        if body == INVALID_HOST_MSG.encode():
            host = dict(scope.get("headers", [])).get(b"host", b"").decode("latin-1")
            body = refused_host_text(host).encode()
            start = {**start, "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                                          (b"content-length", str(len(body)).encode())]}
        await send(start)
        await send({"type": "http.response.body", "body": body})

    await inner(scope, receive, relay)


async def app(scope: dict, receive: Any, send: Any) -> None:
    """ASGI: MLflow's page at ``/`` with our script (``_page``); MLflow's app for every other request, its refusal
    of an unknown Host header naming the flag that allows it (``with_host_hint``)."""
    if scope["type"] == "http" and scope["method"] in ("GET", "HEAD") and scope["path"] == "/":
        await _page(scope, receive, send)
        return
    await with_host_hint(_mlflow(), scope, receive, send)


def create_app() -> Any:
    """The app factory MLflow's plugin mechanism calls (``mlflow.app`` entry point: a function is taken for a
    factory, as ``mlflow.server.auth:create_app`` is)."""
    _mlflow()  # MLflow's app is built at start, not on the first request
    return app
