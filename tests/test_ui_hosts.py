"""`bronchopose ui --allowed-host` (issue 57, item 6): the names it adds, the values it refuses, the 403 it explains.

The server itself (a real `mlflow ui` answering ``Host: review.example``) is tests/test_ui.py's heavy test.
"""

from __future__ import annotations

import asyncio
import socket

import pytest

from bronchocli.config import Config
from bronchocli.errors import BronchoError
from bronchocli.runs.ui import allowed_hosts, check_names, ui_command
from bronchocli.runs.uiapp import refused_host_text, with_host_hint


def test_allowed_names_go_beside_the_machines_own_bare_and_with_the_port():
    got = allowed_hosts("127.0.0.1", 5123, ["review.example", "proxy.internal", "review.example"])
    assert {"review.example", "review.example:5123", "proxy.internal:5123", socket.gethostname()} <= set(got)
    assert got.count("review.example") == 1 and "localhost:*" in got


def test_without_expose_only_the_given_names_are_added(tmp_path):
    cfg = Config(name="hosts").with_values({"runs.uri": f"sqlite:///{tmp_path}/m.db"})
    argv = ui_command(cfg, "127.0.0.1", 5123, 1, allowed=["review.example"])
    names = argv[argv.index("--allowed-hosts") + 1].split(",")
    assert "review.example:5123" in names and socket.gethostname() not in names
    assert "--allowed-hosts" not in ui_command(cfg, "127.0.0.1", 5123, 1)


@pytest.mark.parametrize("bad", ["http://review.example", "review.example/x", "a,b", "", "review.example:80"])
def test_a_value_that_is_no_host_name_is_one_line(bad):
    with pytest.raises(BronchoError, match=r"--allowed-host .*not a host name or address .*review\.example"):
        check_names([bad])
    assert check_names(["review.example", "10.0.0.7", "[fd00::1]", "*.example"]) == ["review.example", "10.0.0.7",
                                                                                       "[fd00::1]", "*.example"]


def _answer(inner, host: str) -> tuple[int, dict, bytes]:
    sent = []

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "method": "GET", "path": "/api/x", "headers": [(b"host", host.encode())]}
    asyncio.run(with_host_hint(inner, scope, None, send))
    return sent[0]["status"], dict(sent[0]["headers"]), b"".join(m.get("body", b"") for m in sent[1:])


def _replying(status: int, body: bytes):
    async def inner(scope, receive, send):  # as MLflow's middleware stack sends it: the body, then an empty last chunk
        await send({"type": "http.response.start", "status": status, "headers": [(b"content-type", b"text/plain")]})
        await send({"type": "http.response.body", "body": body, "more_body": True})
        await send({"type": "http.response.body", "body": b"", "more_body": False})
    return inner


def test_mlflows_host_refusal_names_the_flag_to_pass_and_other_answers_pass_unchanged():
    from mlflow.server.security_utils import INVALID_HOST_MSG

    status, headers, body = _answer(_replying(403, INVALID_HOST_MSG.encode()), "other.example:5000")
    assert status == 403 and "bronchopose ui --expose --allowed-host other.example" in body.decode()
    assert headers[b"content-length"] == str(len(body)).encode()
    assert _answer(_replying(403, b"Permission denied"), "x")[2] == b"Permission denied"  # another 403: as it is
    assert _answer(_replying(200, b"{}"), "x")[:3:2] == (200, b"{}")
    assert "--allowed-host <name>" in refused_host_text("")
