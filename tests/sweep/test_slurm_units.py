"""The Slurm launcher's pieces that need no cluster: its own section (sweep.launchers.slurm), sbatch options, batch
script, idle exit, its worker environment."""

from __future__ import annotations

import shlex

import pytest
from sweep_fakes import fake_runner

from bronchocli.errors import ConfigError
from bronchocli.sweep import SweepStore, Worker, prepare, task
from bronchocli.sweep.launchers import STAGE_ENV, LocalLauncher, SlurmLauncher, detected
from bronchocli.sweep.launchers import slurm as slurm_launcher
from bronchocli.sweep.launchers.slurm import _count, batch_script, check, requeue, sbatch_args
from bronchocli.sweep.task import TaskSpec


@pytest.mark.parametrize("task, n", [("812_3", 1), ("812", 1), ("812_[4-9%2]", 6), ("812_[1,3-4]", 3)])
def test_squeue_ids_are_counted_as_tasks(task, n):
    assert _count(task) == n


def test_sbatch_options_carry_the_slurm_section(make_config):
    cfg = make_config(slurm={"partition": "gpu", "account": "proj", "qos": "high", "timeout_min": 90,
                             "gpus_per_task": 2, "cpus_per_task": 6, "mem_gb": 1.5, "array_parallelism": 3,
                             "signal_delay_s": 45, "additional": {"constraint": "a100", "exclusive": True,
                                                                  "nice": False}})
    args = sbatch_args(cfg, "grid", 5, ["17", "18"])
    for expected in ("--array=0-4%3", "--signal=B:USR1@45", "--requeue", "--open-mode=append", "--time=90",
                     "--gres=gpu:2", "--cpus-per-task=6", "--mem=1536M", "--partition=gpu", "--account=proj",
                     "--qos=high", "--constraint=a100", "--exclusive", "--dependency=afterany:17:18",
                     f"--job-name=bronchopose-{cfg.name}"):
        assert expected in args, (expected, args)
    assert not any(a.startswith("--nice") for a in args)
    assert any(a.startswith(f"--comment=bronchopose:{cfg.name}:") and a.endswith(":grid") for a in args)
    assert any(a.endswith("slurm-logs/%A_%a.log") for a in args)


def test_the_batch_script_runs_setup_then_execs_one_worker(make_config):
    cfg = make_config(slurm={"setup": ["module load cuda", "source venv/bin/activate"], "python": "/opt/py"})
    spec = TaskSpec(config="/x/experiments.yaml", only=("arch=lstm;seed=0",), runner="sweep_fakes:fake_runner",
                    launcher="slurm")
    script = batch_script(cfg, task.command(cfg, spec))
    lines = script.splitlines()
    assert lines[0] == "#!/bin/bash" and "module load cuda" in lines and "source venv/bin/activate" in lines
    assert lines[-1].startswith("exec /opt/py -m bronchocli.sweep.task '{")  # the task's own entry point
    assert "arch=lstm;seed=0" in lines[-1] and "'" + spec.to_json() + "'" in lines[-1]  # quoted for the shell
    assert TaskSpec.from_json(shlex.split(lines[-1])[-1]) == spec  # the task reads back what the launcher wrote
    assert lines.index("module load cuda") < len(lines) - 1
    assert not any(STAGE_ENV in line for line in lines)
    staged = batch_script(cfg, task.command(cfg, spec), "second stage").splitlines()
    assert f"export {STAGE_ENV}='second stage'" in staged and staged[-1] == lines[-1]  # its tasks stop there


def test_an_array_task_loads_the_config_the_command_loaded_and_refuses_a_bad_spec(make_config, capsys):
    cfg = make_config()
    spec = TaskSpec(config=str(cfg.paths.base / "experiments.yaml"), overrides=("train.lr=0.005",),
                    storage="sqlite:///other.db", only=("arch=lstm",), launcher="slurm")
    loaded = TaskSpec.from_json(task.command(cfg, spec)[-1]).load()
    assert loaded.train.lr == 0.005 and loaded.storage.url == "sqlite:///other.db"
    assert TaskSpec.from_json(spec.to_json()).selection() == {"arch": {"lstm"}}
    for bad in ("not json", '{"only": []}', '{"config": "x", "colour": 1}'):
        assert task.main([bad]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: task spec:") and len(err.strip().splitlines()) == 1, err
    assert task.main([TaskSpec(config=str(cfg.paths.base / "nope.yaml")).to_json()]) == 2
    assert "nope.yaml" in capsys.readouterr().err


@pytest.mark.parametrize("section, message", [
    ({"timeout_min": 0}, "sweep.launchers.slurm.timeout_min: 0: input should be greater than or equal to 1 (allowed "
                         "range [1, 525600])"),
    ({"partition": "gpu; rm -rf /"}, "sweep.launchers.slurm.partition"),
    ({"additional": {"array": "0-3"}}, "set by the launcher"),
    ({"additional": {"--constraint": "x"}}, "long option name"),
    ({"setup": ["a\nb"]}, "one shell line"),
    ({"gpus": 2}, "sweep.launchers.slurm.gpus: unknown key 'gpus' (allowed: account, additional,"),
    ({"on_time_limit": "requeu"}, "sweep.launchers.slurm.on_time_limit"),
])
def test_bad_slurm_values_are_refused_when_the_launcher_is_looked_up(cli, make_config, section, message):
    cfg = make_config(slurm=section)  # the core config holds the section as a mapping: the launcher validates it
    with pytest.raises(ConfigError) as info:
        SlurmLauncher.settings(cfg)
    assert message in str(info.value) and len(str(info.value).splitlines()) == 1, str(info.value)
    assert "experiments.yaml:" in str(info.value)  # file:line of the key, as for the core sections
    for args in (["config"], ["sweep", "plan"], ["sweep", "cancel", "--launcher", "slurm", "--dry-run"]):
        code, out, err = cli(*args, "-c", str(cfg.paths.base / "experiments.yaml"))
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, (args, out, err)


def test_the_slurm_worker_environment_reads_its_task_and_requeues_only_on_its_warning(make_config, monkeypatch):
    import signal

    env = SlurmLauncher.environment(make_config(slurm={"on_time_limit": "requeue", "exit_when_idle": False}))
    for key in ("SLURM_ARRAY_JOB_ID", "SLURM_JOB_ID", "SLURM_ARRAY_TASK_ID", "SLURM_CPUS_PER_TASK"):
        monkeypatch.delenv(key, raising=False)
    assert env.job_id is None and env.task_index is None and env.threads is None and not env.exits_when_idle
    assert detected() is None  # `bronchopose train` outside any launcher's job: no warning signal
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "812")
    monkeypatch.setenv("SLURM_JOB_ID", "815")
    monkeypatch.setenv("SLURM_ARRAY_TASK_ID", "3")
    monkeypatch.setenv("SLURM_CPUS_PER_TASK", "6")
    assert (env.job_id, env.task_index, env.threads) == ("812_3", 3, 6)
    assert detected() is SlurmLauncher.Environment  # `bronchopose train` in a Slurm job stops on its warning too
    assert env.warning_signal == signal.SIGUSR1 and env.warning_meaning == "Slurm's time-limit warning"
    requeued = []
    monkeypatch.setattr(slurm_launcher, "requeue", lambda task: requeued.append(task) or True)
    env.done(signal.SIGTERM)  # scancel: the task is not requeued
    env.done(None)
    assert requeued == []
    env.done(signal.SIGUSR1)
    assert requeued == ["812_3"]
    LocalLauncher.environment(make_config()).done(signal.SIGUSR1)  # no warning signal: nothing to do
    assert LocalLauncher.Environment.warning_signal is None


def test_the_checks_refuse_stores_and_folders_compute_nodes_cannot_share(make_config, monkeypatch, tmp_path):
    monkeypatch.setattr("shutil.which", lambda name: "/usr/bin/" + name)
    cfg = make_config()
    with pytest.raises(Exception, match="storage.url sqlite.*SQLite claims table"):
        check(cfg)
    with pytest.raises(Exception, match="runs.uri sqlite.*MLflow store"):
        check(make_config(storage="postgresql://u@db.example/sweeps"))
    with pytest.raises(Exception, match="runs.checkpoints /tmp/ck: a node-local folder"):
        check(make_config(storage="postgresql://u@db.example/sweeps",
                          runs={"uri": "postgresql://u@db.example/mlflow", "artifacts": "/srv/a",
                                    "checkpoints": "/tmp/ck"}, dataset={"root": "/srv/data"}))
    # with slurm.shared_filesystem: true the same configs pass these checks (tests/sweep/test_slurm.py submits them)


def test_status_reads_the_slurm_task_from_the_worker_id():
    from bronchocli.sweep.worker import job_of

    assert job_of("node7:4242 slurm 812_3 gpu0") == "812_3"
    assert job_of("node7:4242 gpu0") is None and job_of(None) is None


def test_a_worker_that_exits_when_idle_does_not_wait_for_cells_held_elsewhere(make_config, fake_dir):
    cfg = make_config(archs=("baseline",), sweep={"poll_s": 30.0, "stale_after_s": 600.0})  # held, never stale
    store = SweepStore(cfg.paths.storage_url)
    plan = prepare(cfg, store, dataset=False)
    claim = store.claim(cfg.name, [c.key for c in plan.cells], "elsewhere:1", max_retries=1, stale_after_s=60)
    assert claim is not None
    worker = Worker(cfg, plan.cells, store, fake_runner, exit_when_idle=True)
    assert worker.run() == 0 and worker.idle  # returned at once: poll_s of 30 s was never waited
    assert store.rows(cfg.name)[0].worker == "elsewhere:1"


def test_launcher_flags_are_checked_and_the_config_can_choose_slurm(cli, make_config, tmp_path, monkeypatch):
    cfg = make_config(sweep={"launcher": "slurm"})
    path = str(cfg.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "-c", path, "--launcher", "local", "--detach")
    assert code == 2 and "--detach: launcher local runs its workers in this command" in out + err
    code, out, err = cli("sweep", "-c", path, "--launcher", "pbs")
    assert code == 2 and "--launcher pbs: must be one of local, slurm" in out + err
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    code, out, err = cli("sweep", "-c", path)  # sweep.launcher: slurm, and no sbatch here
    assert code == 2 and "sbatch not found" in out + err and len((out + err).strip().splitlines()) == 1
    assert not (tmp_path / "sweep.db").exists()


def test_a_refused_requeue_is_retried_and_logged_not_ignored(tmp_path, monkeypatch, caplog):
    fake = tmp_path / "bin" / "scontrol"
    fake.parent.mkdir()
    fake.write_text('#!/bin/sh\necho "$@" >> "$(dirname "$0")/calls"\n'
                    'echo "scontrol: error: Requested operation is presently disabled for job 7_1" >&2\nexit 1\n')
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake.parent}:/usr/bin:/bin")
    monkeypatch.setattr(slurm_launcher.time, "sleep", lambda s: None)
    assert requeue("7_1") is False
    assert (fake.parent / "calls").read_text().splitlines() == ["requeue 7_1"] * 3
    # the refusal is announced once with its reason and the attempt count (the same error again goes to debug),
    # then the error of the last try
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and "presently disabled for job 7_1" in warnings[0] and "attempt 2/3" in warnings[0], \
        warnings
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert len(errors) == 1 and "7_1 was not requeued" in errors[0] and "presently disabled" in errors[0]
