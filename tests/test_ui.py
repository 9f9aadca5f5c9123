"""`bronchopose ui` really serves the configured MLflow store on 127.0.0.1."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest

MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ui_serves_the_store(tmp_path):
    (tmp_path / "experiments.yaml").write_text("name: ui-test\n")
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-c", MAIN, "ui", "--port", str(port)], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env={**os.environ, "COLUMNS": "200"})
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=2) as response:
                    assert response.status == 200 and response.read().strip() == b"OK"
                    break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"the UI did not come up:\n{proc.stdout.read() if proc.poll() is not None else ''}")
                time.sleep(0.2)
        assert (tmp_path / "runs" / "mlflow.db").is_file()  # it serves the config's store
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)


def test_ui_refuses_a_remote_tracking_server(tmp_path, cli):
    (tmp_path / "experiments.yaml").write_text("name: t\ntracking: {uri: 'http://mlflow.example:5000'}\n")
    code, _, err = cli("ui", "-c", str(tmp_path / "experiments.yaml"))
    assert code == 2 and "already a server" in err
