"""Issue 32.4: a password given to `sweep run --launcher slurm` never reaches the batch script, the sbatch argv, the
task's command line (what `ps` shows) or the console; the task gets it from a file only the user can read."""

from __future__ import annotations

import json
import shlex
import stat

import pytest
from tinydata import write_tiny_dataset

from bronchocli.sweep import task
from bronchocli.sweep.task import TaskSpec

PLANTED = {"userinfo": "Pl4nt-userinfo", "query": "Pl4nt-query", "env": "Pl4nt-env", "pgpass": "Pl4nt-pgpass"}
FAKE_SBATCH = """#!/bin/sh
# records every call (one line of shell-quoted arguments) and the batch script it was given
printf '%s\\n' "$*" >> "$(dirname "$0")/calls"
for a in "$@"; do last="$a"; done
[ -f "$last" ] && cat "$last" >> "$(dirname "$0")/scripts"
case "$*" in *--test-only*) echo "sbatch: Job 1 to start at now" >&2;; *) echo "101";; esac
"""


@pytest.fixture
def fake_slurm(tmp_path, monkeypatch):
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    (bin_ / "sbatch").write_text(FAKE_SBATCH)
    (bin_ / "squeue").write_text('#!/bin/sh\nprintf \'%s\\n\' "$*" >> "$(dirname "$0")/calls"\n')
    for f in bin_.iterdir():
        f.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_}:{__import__('os').environ['PATH']}")
    return bin_


@pytest.fixture
def secrets_env(tmp_path, monkeypatch):
    """PGPASSWORD and a .pgpass with planted passwords (libpq reads both; trust auth ignores them)."""
    pgpass = tmp_path / "pgpass"
    pgpass.write_text(f"127.0.0.1:5432:*:postgres:{PLANTED['pgpass']}\n")
    pgpass.chmod(0o600)
    monkeypatch.setenv("PGPASSFILE", str(pgpass))
    monkeypatch.setenv("PGPASSWORD", PLANTED["env"])


def _planted_url(pg_url: str) -> str:
    """``pg_url`` with a password in the userinfo and another as a ``password`` query parameter."""
    return (pg_url.replace("postgres@", f"postgres:{PLANTED['userinfo']}@")
            + f"&password={PLANTED['query']}&sslmode=disable")


def _leaks(text: str) -> list[str]:
    return [form for form, secret in PLANTED.items() if secret in text]


@pytest.mark.parametrize("how", ["--set", "--storage"])
def test_no_password_reaches_the_batch_script_the_sbatch_argv_or_the_task_command_line(
        cli, make_config, fake_slurm, secrets_env, pg_url, how, tmp_path):
    # a dataset in place: without one the submission would first render the default dataset (3 patients x 4
    # lobes x 6 trajectories, most of this test's time), which no assertion here is about
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    cfg = make_config(slurm={"shared_filesystem": True})
    url = _planted_url(pg_url)
    given = ["--set", f"storage.url={url}"] if how == "--set" else ["--storage", url]
    code, out, err = cli("sweep", "run", "-c", str(cfg.paths.base / "experiments.yaml"), "--launcher", "slurm",
                         "--detach", *given, "--set", "train.lr=0.001")
    assert code == 0, out + err
    calls = (fake_slurm / "calls").read_text()
    scripts = (fake_slurm / "scripts").read_text()
    logs = cfg.paths.base / "runs" / "slurm-logs"
    on_disk = {p.name: p.read_text() for p in logs.glob("*.sh")}
    assert on_disk and "submitted Slurm array job 101" in out
    for where, text in {"console": out + err, "sbatch argv": calls, "batch script": scripts, **on_disk}.items():
        assert _leaks(text) == [], (where, text)
    # what `ps` shows for a running task: the exec line of the script, as the shell splits it
    argv = shlex.split(scripts.strip().splitlines()[-1])[1:]
    assert argv[1:3] == ["-m", task.MODULE] and not _leaks(" ".join(argv))
    spec = TaskSpec.from_json(argv[-1])
    assert spec.secrets and "***" in json.dumps(spec.overrides) + str(spec.storage)
    secret_file = spec.secrets
    mode = stat.S_IMODE(__import__("os").stat(secret_file).st_mode)
    assert mode == 0o600, oct(mode)  # only the user can read it
    # the task puts the real values back, and they reach the same store
    loaded = spec.load()
    assert loaded.paths.storage_url == url and loaded.train.lr == 0.001


def test_a_spec_without_secrets_is_left_as_it_is_and_a_missing_secret_file_is_one_line(make_config, tmp_path,
                                                                                        capsys):
    cfg = make_config()
    plain = TaskSpec(config=str(cfg.paths.base / "experiments.yaml"), overrides=("train.lr=0.005",), launcher="slurm")
    assert TaskSpec.from_json(task.command(cfg, plain)[-1]).secrets is None
    sealed = TaskSpec.from_json(task.command(cfg, TaskSpec(
        config=plain.config, overrides=("storage.url=postgresql://h/db?password=hunter22",), launcher="slurm"))[-1])
    assert sealed.overrides == ("storage.url=postgresql://h/db?password=***",)
    assert task.command(cfg, plain) == task.command(cfg, plain)  # the same values: the same file, nothing piles up
    __import__("os").unlink(sealed.secrets)
    assert task.main([sealed.to_json()]) == 2
    err = capsys.readouterr().err
    assert "secret file" in err and "submit the sweep again" in err and len(err.strip().splitlines()) == 1
