"""`bronchopose sweep` and `bronchopose status` end to end with a fake runner: plan, exit codes, Ctrl-C, redaction."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time

import pytest
from sweep_fakes import FAKE, HERE, calls, fake_runner, runs_by_cell
from tinydata import write_tiny_dataset

from bronchocli.sweep import FINISHED, PENDING, SweepStore, Worker, prepare, worker_config


@pytest.fixture
def project(make_config, tmp_path):
    """A config with a (tiny, already present) dataset: `sweep` generates nothing."""
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    return make_config(grid_order=True)  # baseline, then lstm: the Ctrl-C test interrupts the second


def cells_of(cfg):
    return {r.label.split("/")[0]: r for r in SweepStore(cfg.paths.storage_url).rows(cfg.name)}


def test_sweep_runs_the_plan_exits_1_on_failures_and_status_reports_them(cli, project, fake_dir):
    path = str(project.paths.base / "experiments.yaml")
    (fake_dir / "fail-lstm").write_text("1")  # lstm fails its first run; max_retries=0: no automatic retry
    code, out, err = cli("sweep", "plan", "-c", path)
    assert code == 0 and "2 cells: 0 finished" in out and "dry run" in out
    assert not (project.paths.base / "sweep.db").exists()  # a dry run writes nothing
    code, out, err = cli("sweep", "-c", path, "--set", "sweep.max_retries=0", "--workers", "2", *FAKE)
    assert code == 1, out + err
    assert "done 1/2" in out and "failed lstm/mse/personalized/s0/world: fake failure" in out
    code, out, _ = cli("status", "-c", path, "--set", "sweep.max_retries=0")
    # each cell by its run name (model, loss, seed first); the headline ratios and skills, pair and accumulated
    assert code == 0 and "fake failure" in out and re.search(r"\+LSTM MSE\+MSE · s0\S*.*\s+failed\s", out)
    base = cells_of(project)["baseline"]
    line = next(line for line in out.splitlines() if base.run_id in line)
    metric = int(base.cell_key[:6], 16) / 2**24  # what the fake logged as pair.pos_l2.mean (acc: 10x; refs 0.5, 4)
    acc_skill = 1 - 10 * metric / 4.0
    assert "finished" in line and "Baseline MSE+MSE · s0" in line
    assert f"{metric / 0.5:.4g}" in line and f"{1 - metric / 0.5:.4g}" in line and f"{10 * metric / 4:.4g}" in line
    assert f"{acc_skill:.4g}" + (" †" if acc_skill <= 0 else "") in line
    code, out, _ = cli("sweep", "-c", path, "--set", "sweep.max_retries=0", "--retry-failed", *FAKE)
    assert code == 0 and "done 2/2" in out
    code, out, _ = cli("sweep", "-c", path, *FAKE)  # nothing left: no worker runs anything again
    assert code == 0 and "2 finished" in out
    assert calls(base.cell_key) == 1 and calls(cells_of(project)["lstm"].cell_key) == 2
    assert runs_by_cell(project) == {r.cell_key: 1 for r in cells_of(project).values()}


@pytest.mark.parametrize("args, message", [
    (["plan", "--only", "arch=transformer"], "arch 'transformer' must be one of"),
    (["plan", "--only", "arch=offsetnet"], "no cell of the plan has that arch"),
    (["plan", "--only", "colour=red"], "key one of arch, rot_loss"),
    (["plan", "--workers", "0"], ""),
    (["run", "--runner", "no_such_module:run"], "--runner no_such_module:run: cannot import no_such_module"),
    (["run", "--runner", "sweep_fakes"], "must be module:function"),
    (["run", "--runner", "sweep_fakes:no_such_runner"], "module sweep_fakes has no no_such_runner"),
])
def test_bad_input_exits_2(cli, project, args, message):
    code, _, err = cli("sweep", *args, "-c", str(project.paths.base / "experiments.yaml"))
    assert code == 2 and message in err


def test_only_selects_cells(cli, project):
    code, out, _ = cli("sweep", "plan", "-c", str(project.paths.base / "experiments.yaml"), "--only", "arch=lstm")
    assert code == 0 and "1 cells" in out and "lstm/mse" in out and "baseline/mse" not in out


@pytest.mark.parametrize("signum, exit_code", [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_ctrl_c_stops_the_sweep_with_130_and_a_rerun_resumes_the_cell(cli, project, fake_dir, tmp_path, signum,
                                                                      exit_code):
    """Ctrl-C, SIGTERM and SIGHUP (the terminal closed) alike: the cell is given back at once (PENDING, not left
    RUNNING to go stale), one line, the shell's exit code of the signal (issue 49)."""
    path = str(project.paths.base / "experiments.yaml")
    (fake_dir / "block-lstm").touch()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")])}
    code = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
    proc = subprocess.Popen([sys.executable, "-c", code, "sweep", "-c", path, *FAKE],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    end = time.monotonic() + 120
    while not any(fake_dir.glob("started-*")):  # wait for the worker to be inside the lstm cell
        assert proc.poll() is None and time.monotonic() < end, proc.stdout.read() if proc.poll() is not None else ""
        time.sleep(0.05)
    proc.send_signal(signum)  # SIGINT: what Ctrl-C sends to the foreground process
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == exit_code, out + err
    # on stderr, naming the signal, worded as train's (issue 60): "interrupted: SIGTERM received (...); ..."
    assert f"interrupted: {signal.Signals(signum).name} received" in " ".join(err.split()), err
    assert "run the same command again to resume" in " ".join(err.split()) and "Traceback" not in out + err
    assert cells_of(project)["lstm"].state == PENDING and cells_of(project)["baseline"].state == FINISHED
    assert runs_by_cell(project, "KILLED") == {cells_of(project)["lstm"].cell_key: 1}
    (fake_dir / "block-lstm").unlink()
    store = SweepStore(project.paths.storage_url)
    assert Worker(project, prepare(project, store).cells, store, fake_runner).run() == 0  # the re-run
    assert calls(cells_of(project)["baseline"].cell_key) == 1 and calls(cells_of(project)["lstm"].cell_key) == 2
    assert runs_by_cell(project) == {r.cell_key: 1 for r in cells_of(project).values()}


@pytest.mark.postgres
def test_storage_passwords_never_appear_in_output_logs_or_runs(cli, project, fake_dir, pg_url):
    url = pg_url.replace("postgresql+psycopg://postgres@", "postgresql://postgres:topsecret@")  # trust auth ignores it
    path = str(project.paths.base / "experiments.yaml")
    assert worker_config(project.with_values({"storage.url": url})).storage.url.count("topsecret") == 0
    outputs = []
    for args in (["sweep", "plan"], ["sweep", *FAKE], ["status"]):
        code, out, err = cli(*args, "-c", path, "--storage", url)
        assert code == 0, out + err
        outputs.append(out + err)
    text = "\n".join(outputs)
    assert "topsecret" not in text and "postgres:***@" in text
    logs = [p.read_text() for p in (project.paths.base / "runs" / "sweep-logs").rglob("*.log")]
    markers = [p.read_text() for p in (fake_dir / "calls").iterdir()]  # storage.url of the runner's config
    assert logs and markers and not any("topsecret" in t for t in logs + markers)
    assert all("postgres:***@" in m for m in markers)


def test_unreachable_storage_is_a_clear_error_without_the_password(cli, project):
    code, _, err = cli("status", "-c", str(project.paths.base / "experiments.yaml"),
                       "--storage", "postgresql://alice:hunter2@127.0.0.1:1/db")
    assert code == 2 and "hunter2" not in err and "alice:***@127.0.0.1:1" in err
