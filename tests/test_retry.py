"""The one retry loop: transient failures are retried within a bound, anything else is raised at once."""

from __future__ import annotations

import pytest

from bronchocli.retry import is_transient_db, retry


class Flaky:
    def __init__(self, failures: int, exc: BaseException):
        self.failures, self.exc, self.calls = failures, exc, 0

    def __call__(self) -> str:
        self.calls += 1
        if self.calls <= self.failures:
            raise self.exc
        return "ok"


def fast(**kw):
    return dict(transient=lambda e: isinstance(e, ConnectionError), what="test", first_delay_s=0.001, **kw)


def test_transient_failures_are_retried_until_the_call_succeeds():
    fn = Flaky(3, ConnectionError("refused"))
    assert retry(fn, **fast(attempts=4)) == "ok" and fn.calls == 4


def test_the_attempt_bound_raises_the_last_error_or_the_give_up_replacement():
    fn = Flaky(5, ConnectionError("refused"))
    with pytest.raises(ConnectionError):
        retry(fn, **fast(attempts=3))
    assert fn.calls == 3
    with pytest.raises(RuntimeError, match="gave up after refused"):
        retry(Flaky(5, ConnectionError("refused")), **fast(attempts=2),
              give_up=lambda e: RuntimeError(f"gave up after {e}"))


def test_the_time_bound_stops_a_failure_that_never_ends():
    fn = Flaky(10**9, ConnectionError("refused"))
    with pytest.raises(ConnectionError):
        retry(fn, **fast(bound_s=0.02))
    assert 1 < fn.calls < 10**9


def test_a_failure_that_is_not_transient_is_raised_at_once():
    fn = Flaky(1, ValueError("no such column"))
    with pytest.raises(ValueError):
        retry(fn, **fast(attempts=5))
    assert fn.calls == 1


def test_a_retry_needs_a_bound():
    with pytest.raises(ValueError, match="bound_s or attempts"):
        retry(lambda: 1, transient=lambda e: True, what="x")


def test_a_warning_per_retry_hides_passwords(caplog):
    fn = Flaky(1, ConnectionError("could not connect to postgresql://bob:hunter2@db/x"))
    with caplog.at_level("WARNING", logger="bronchocli.retry"):
        retry(fn, **fast(attempts=2))
    assert "hunter2" not in caplog.text and "retrying" in caplog.text


@pytest.mark.parametrize("text, transient", [
    ("database is locked", True), ("FATAL: the database system is starting up", True),
    ("server closed the connection unexpectedly", True), ("no such table: runs", False),
    ("syntax error at or near", False)])
def test_database_errors_are_judged_by_their_text(text, transient):
    assert is_transient_db(RuntimeError(text)) is transient


def test_a_transient_cause_makes_the_wrapping_error_transient():
    try:
        try:
            raise ConnectionError("connection refused")
        except ConnectionError as inner:
            raise RuntimeError("store request failed") from inner
    except RuntimeError as outer:
        assert is_transient_db(outer)
