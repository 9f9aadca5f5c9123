"""An MLflow server that answers 5xx (its database is away) is waited out within runs.busy_timeout_s, like a
locked SQLite file; metrics logged meanwhile are kept, not fatal (issue 30, item 3).

The server here is a real HTTP server on loopback that answers 503 as MLflow's server does while its
PostgreSQL is down, then 200; the client is MLflow's own (its HTTP retries are the ones the bound covers)."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from mlflow.entities import Metric
from mlflow.tracking import MlflowClient

from bronchocli.errors import MlflowBusy, MlflowUnreachable, resumable
from bronchocli.retry import is_transient_store
from bronchocli.runs.client import BusyRetryClient, MetricBuffer, set_http_limits


class Flaky(BaseHTTPRequestHandler):
    down = 0  # requests still answered 503
    seen: list[str] = []

    def do_POST(self):  # noqa: N802 - http.server's name
        self.rfile.read(int(self.headers.get("Content-Length") or 0))
        type(self).seen.append(self.path)
        if type(self).down > 0:
            type(self).down -= 1
            self.send_response(503)
            self.end_headers()
            return
        body = json.dumps({}).encode()
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.fixture
def server(monkeypatch):
    set_http_limits(5.0)
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")  # each call fails at the first 503: fast tests
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR", "0")
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Flaky)
    Flaky.down, Flaky.seen = 0, []
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()


def test_an_mlflow_servers_503_answers_are_retried_within_the_bound_then_the_call_succeeds(server):
    Flaky.down = 3
    client = BusyRetryClient(MlflowClient(tracking_uri=server), 30.0, server)
    client.log_batch("r1", metrics=[Metric("val_loss", 1.0, 0, 1)])
    assert Flaky.seen == ["/api/2.0/mlflow/runs/log-batch"] * 4  # three 503s waited out, the fourth answered


def test_beyond_the_bound_an_outage_is_mlflowbusy_a_resumable_failure(server):
    Flaky.down = 10**6
    # a bound of 2 s, not less: the first call of a cold process (MLflow's client warming up) can take longer
    # than a few tenths of a second on a loaded 2-core machine, and then nothing is left for a retry
    client = BusyRetryClient(MlflowClient(tracking_uri=server), 2.0, server)
    with pytest.raises(MlflowBusy, match=r"stayed busy or unavailable for 2(\.0)? s .*503.*during log_batch") as info:
        client.log_batch("r1", metrics=[Metric("val_loss", 1.0, 0, 1)])
    assert resumable(info.value) and resumable(MlflowUnreachable("x"))
    assert len(Flaky.seen) > 1  # retried, not given up at the first answer


def test_a_client_error_is_not_an_outage():
    assert not is_transient_store(RuntimeError("RESOURCE_DOES_NOT_EXIST: Run 'x' not found"))
    assert not is_transient_store(ValueError("INVALID_PARAMETER_VALUE: bad metric"))
    assert is_transient_store(RuntimeError("API request to http://h/api failed with exception HTTPConnectionPool"
                                           "(host='h', port=5000): Max retries exceeded with url: /api (Caused by "
                                           "ResponseError('too many 503 error responses'))"))


def test_metrics_logged_during_an_outage_are_kept_and_sent_in_order_when_the_server_answers(server):
    Flaky.down = 10**6
    client = BusyRetryClient(MlflowClient(tracking_uri=server), 0.3, server)
    out = MetricBuffer(client, "r1")
    out.log({"val_loss": 1.0}, 2)  # the store is away: not raised, kept
    out.log({"val_loss": 0.5}, 4)
    assert [step for step, _ in out.pending] == [2, 4]
    Flaky.down = 0
    before = len(Flaky.seen)
    out.log({"val_loss": 0.25}, 6)
    assert out.pending == [] and len(Flaky.seen) - before == 3  # the two kept, then the new one
    Flaky.down = 10**6
    out.log({"val_loss": 0.2}, 8)
    with pytest.raises(MlflowBusy):  # the run's end waits (bounded) for the store: then the failure is resumable
        out.flush(wait=True)
    assert [step for step, _ in out.pending] == [8]
