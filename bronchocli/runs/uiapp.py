"""The server app `bronchopose ui` runs: MLflow's own app behind a front page at the bare root (issue 36.5).

MLflow 3.17's UI chooses its mode (GenAI or model training) from the URL's
``workflowType`` or else the browser's ``localStorage["mlflow.workflowType_v1"]``
(default GenAI), which only its sidebar's GenAI / Model training switch writes;
the experiment tag ``mlflow.experimentKind`` is not read for it (a feature flag
compiled into the UI), and a ``workflowType`` in the URL is not stored. So a
fresh browser that opens the UI and clicks the experiment lands on the GenAI
overview. No setting of MLflow's server presets it, and the fragment of a URL
(where the UI's routes live) never reaches a server.

This app is MLflow's (``mlflow.server.fastapi_app:app``, unchanged) with one
page in front of it: a request for the bare root ``/`` (no query) gets a small
page of ours whose script

* stores ``"machine_learning"`` under MLflow's own key for that switch when the
  browser has no value there yet (what one click on "Model training" stores; a
  choice the user made is kept), so MLflow's own navigation -- Experiments,
  then the experiment -- opens the runs table in the model-training view;
* forwards to MLflow's UI at ``/?ui=bronchopose`` with the address's fragment
  (a link into the UI keeps its page), or, when there is none, with the
  experiment's runs table on the headline view (``LANDING_ENV``: the fragment
  of ``views.runs_table_url``).

Every other request (the UI at ``/?ui=bronchopose``, its files, the REST API)
goes to MLflow's app as it is. MLflow loads it through its documented app
plugin mechanism (the ``mlflow.app`` entry point ``bronchopose``, as its
``basic-auth`` app is: ``mlflow ui --app-name bronchopose``); nothing in MLflow
is patched. ``tests/training/test_ui_browser.py`` asserts the landing in a real
browser, so an MLflow release that renames the key fails there.
"""

from __future__ import annotations

import html
import json
import os
from typing import Any

APP_NAME = "bronchopose"  # the mlflow.app entry point (pyproject.toml)
LANDING_ENV = "BRONCHOPOSE_UI_LANDING"  # the fragment to land on when the root is opened without one
WORKFLOW_KEY = "mlflow.workflowType_v1"  # MLflow 3.17's localStorage key of the GenAI / Model training switch
MODEL_TRAINING = "machine_learning"
UI_PATH = "/?ui=bronchopose"  # MLflow's UI (its app serves index.html at / whatever the query)

_mlflow_app: Any = None


def front_page(landing: str) -> bytes:
    """The page served at the bare root: the model-training mode unless chosen, then MLflow's UI at the address's
    fragment, or at ``landing`` when it has none."""
    script = (
        "(function () {"
        f"var key = {json.dumps(WORKFLOW_KEY)};"
        f"try {{ if (window.localStorage.getItem(key) === null) "
        f"window.localStorage.setItem(key, JSON.stringify({json.dumps(MODEL_TRAINING)})); }} catch (e) {{}}"
        f"var hash = window.location.hash && window.location.hash !== '#' ? window.location.hash : "
        f"{json.dumps(landing)};"
        f"window.location.replace({json.dumps(UI_PATH)} + hash);"
        "})();"
    ).replace("</", "<\\/")
    fallback = html.escape(UI_PATH + landing)
    return ("<!doctype html><html><head><meta charset=\"utf-8\"><title>MLflow</title>"
            f"<script>{script}</script></head><body><noscript><a href=\"{fallback}\">MLflow</a></noscript>"
            "</body></html>").encode()


def _mlflow() -> Any:
    global _mlflow_app
    if _mlflow_app is None:
        from mlflow.server.fastapi_app import app as mlflow_app  # lazy: builds MLflow's whole server app

        _mlflow_app = mlflow_app
    return _mlflow_app


async def app(scope: dict, receive: Any, send: Any) -> None:
    """ASGI: the front page for ``GET /`` without a query when a landing is set; MLflow's app for the rest."""
    landing = os.environ.get(LANDING_ENV)
    if (landing and scope["type"] == "http" and scope["method"] in ("GET", "HEAD") and scope["path"] == "/"
            and not scope.get("query_string")):
        body = front_page(landing)
        await send({"type": "http.response.start", "status": 200,
                    "headers": [(b"content-type", b"text/html; charset=utf-8"), (b"cache-control", b"no-store"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": b"" if scope["method"] == "HEAD" else body})
        return
    await _mlflow()(scope, receive, send)


def create_app() -> Any:
    """The app factory MLflow's plugin mechanism calls (``mlflow.app`` entry point: a function is taken for a
    factory, as ``mlflow.server.auth:create_app`` is)."""
    _mlflow()  # MLflow's app is built at start, not on the first request
    return app
