"""The one retry loop: transient failures are retried within a bound, anything else is raised at once."""

from __future__ import annotations

import shutil

import pytest

from bronchocli.retry import (
    RACE_RETRIES,
    disk_full,
    disk_full_line,
    is_transient_db,
    is_transient_store,
    is_write_race,
    planned_attempts,
    retry,
    with_races,
)


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


# -- a write that lost a unique-key race (issue 37.1) ----------------------------------------------------------

def sqlite_unique_violation() -> BaseException:
    """SQLAlchemy's IntegrityError from a real SQLite insert of a key that is there already."""
    from sqlalchemy import create_engine, text

    engine = create_engine("sqlite://")
    with engine.begin() as conn:
        conn.execute(text("CREATE TABLE datasets (name TEXT PRIMARY KEY)"))
        conn.execute(text("INSERT INTO datasets VALUES ('tiny')"))
    try:
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO datasets VALUES ('tiny')"))
    except Exception as exc:  # noqa: BLE001 - the error under test
        return exc
    raise AssertionError("the duplicate insert succeeded")


@pytest.mark.parametrize("exc, race", [
    (RuntimeError('RestException: BAD_REQUEST: (psycopg2.errors.UniqueViolation) duplicate key value violates '
                  'unique constraint "dataset_pk"\nDETAIL:  Key (experiment_id, name, digest)=(1, t, d) exists.'),
     True),
    (sqlite_unique_violation(), True),
    (RuntimeError("(pymysql.err.IntegrityError) (1062, \"Duplicate entry '1-t' for key 'PRIMARY'\")"), True),
    (RuntimeError('insert or update on table "inputs" violates foreign key constraint "fk_run"'), False),
    (RuntimeError("INVALID_PARAMETER_VALUE: Changing param values is not allowed"), False),
    (RuntimeError("database is locked"), False)])
def test_a_unique_key_conflict_is_judged_a_write_race(exc, race):
    assert is_write_race(exc) is race
    assert not is_transient_store(exc) or not race  # not an outage: its own, shorter allowance


def test_a_write_race_is_retried_a_few_times_then_raised_like_any_conflict():
    lost = sqlite_unique_violation()
    once = Flaky(1, lost)  # the row exists now: the same call succeeds
    assert retry(once, transient=with_races(lambda e: False), what="t", attempts=10, first_delay_s=0.001) == "ok"
    assert once.calls == 2
    always = Flaky(10**9, lost)  # a lasting conflict is a real one: raised after RACE_RETRIES more tries
    with pytest.raises(type(lost)):
        retry(always, transient=with_races(lambda e: False), what="t", attempts=100, first_delay_s=0.001)
    assert always.calls == RACE_RETRIES + 1
    outage = Flaky(5, ConnectionError("refused"))  # the wrapped judgement still rules outages, uncounted
    assert retry(outage, transient=with_races(lambda e: isinstance(e, ConnectionError)), what="t", attempts=10,
                 first_delay_s=0.001) == "ok"


def test_the_platforms_mlflow_client_retries_a_lost_race_and_an_outage_but_no_other_error():
    from mlflow.exceptions import MlflowException

    from bronchocli.runs.client import BusyRetryClient

    class Store:
        def __init__(self, errors):
            self.errors, self.calls = list(errors), 0

        def log_inputs(self, run_id, datasets=None):
            self.calls += 1
            if self.errors:
                raise self.errors.pop(0)
            return run_id

    race = MlflowException('(psycopg2.errors.UniqueViolation) duplicate key value violates unique constraint '
                           '"dataset_pk"')
    store = Store([race])
    assert BusyRetryClient(store, 5.0, "http://mlflow").log_inputs("r1") == "r1" and store.calls == 2
    wrong = Store([MlflowException("INVALID_PARAMETER_VALUE: run r1 is not active")])
    with pytest.raises(MlflowException, match="not active"):
        BusyRetryClient(wrong, 5.0, "http://mlflow").log_inputs("r1")
    assert wrong.calls == 1


def test_an_outage_is_announced_once_with_its_attempt_count_not_once_per_retry(caplog):
    """Issue 60: a storage outage printed ~10 identical lines; now one, saying which attempt of how many."""
    fn = Flaky(6, ConnectionError("could not connect to server"))
    with caplog.at_level("WARNING", logger="bronchocli.retry"):
        assert retry(fn, **fast(attempts=10)) == "ok"
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned == ["test: could not connect to server; retrying (attempt 2/10)..."]
    caplog.clear()
    errors = [ConnectionError("could not connect to server")] * 2 + [ConnectionError("connection refused")] * 2

    def changing():
        if errors:
            raise errors.pop(0)
        return "ok"

    with caplog.at_level("WARNING", logger="bronchocli.retry"):
        assert retry(changing, **fast(attempts=10)) == "ok"
    assert [r.getMessage() for r in caplog.records] == [  # a new error is announced; its repeats are not
        "test: could not connect to server; retrying (attempt 2/10)...",
        "test: connection refused; retrying (attempt 4/10)..."]


def test_a_time_bound_gives_the_most_attempts_its_pauses_allow():
    assert planned_attempts(None, 7, 0.05, 2.0) == 7
    assert planned_attempts(1.0, None, 0.05, 2.0) == 6  # pauses 0.05, 0.1, 0.2, 0.4, 0.8: the fifth passes 1 s
    assert planned_attempts(1.0, 3, 0.05, 2.0) == 3


def test_a_copy_that_fills_a_disk_names_the_file_written_and_the_full_file_system(tmp_path):
    """Issue 60: shutil's copy (MLflow's artifact upload) names its temporary source first; the line names the
    destination, the file system that is full (its mount point) and the space free on it."""
    from mounts import tmpfs

    source = tmp_path / "tmpabc" / "predictions.csv"
    source.parent.mkdir()
    source.write_bytes(b"x" * 300_000)
    with tmpfs(tmp_path / "small", "256k") as disk:
        (disk / "artifacts").mkdir()
        with pytest.raises(OSError) as info:
            shutil.copyfile(source, disk / "artifacts" / "predictions.csv")
        why, file = disk_full(info.value)
        assert file == str(disk / "artifacts" / "predictions.csv")
        line = disk_full_line(file, why)
    assert line.startswith(f"{disk / 'artifacts' / 'predictions.csv'}: disk full (No space left on device; ")
    assert f"free on the file system mounted at {disk})" in line and "tmpabc" not in line


def test_mlflows_own_line_for_a_5xx_answer_is_transient_and_a_4xx_is_not():
    """MLflow raises this line for a 5xx its HTTP client did not retry (its cached session's policy is per process):
    a server briefly away, worth waiting for; a 4xx is the request's own fault."""
    from bronchocli.retry import is_transient_store

    line = "API request to endpoint /api/2.0/mlflow/runs/log-batch failed with error code {} != 200. Response body: ''"
    assert all(is_transient_store(Exception(line.format(code))) for code in (500, 502, 503, 504))
    assert not any(is_transient_store(Exception(line.format(code))) for code in (400, 403, 404))
