"""The launcher seam (issue 38, item 1): a launcher written in one file plus one registration runs a sweep exactly
once; the worker id is structured data; the sweep's verbs take only their own options (item 2)."""

from __future__ import annotations

import re

import pytest
from sweep_fakes import FAKE, calls, runs_by_cell
from tinydata import write_tiny_dataset

from bronchocli.sweep import FINISHED, SweepStore, WorkerId
from bronchocli.sweep.launchers import launcher_class, names


@pytest.fixture
def project(make_config, tmp_path):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    return make_config()


def test_a_launcher_in_one_file_plus_one_registration_runs_a_two_cell_sweep_exactly_once(cli, project, fake_dir):
    import subprocess_launcher  # its one registration: `register(SubprocessLauncher)` at its end

    assert "subprocess" in names() and launcher_class("subprocess") is subprocess_launcher.SubprocessLauncher
    path = str(project.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "subprocess", *FAKE)
    assert code == 0, out + err
    assert re.search(r"submitted subprocess job \S+: 2 worker\(s\) for stage grid", out), out
    rows = SweepStore(project.paths.storage_url).rows(project.name)
    assert len(rows) == 2 and {r.state for r in rows} == {FINISHED}
    assert [calls(r.cell_key) for r in rows] == [1, 1]  # each cell ran once
    assert runs_by_cell(project) == {r.cell_key: 1 for r in rows}  # and left one FINISHED MLflow run
    workers = [WorkerId.parse(r.worker) for r in rows]  # who finished each cell: a worker of that launcher
    assert all(w is not None and w.launcher == "subprocess" and w.job for w in workers), [r.worker for r in rows]
    code, out, _ = cli("sweep", "run", "-c", path, "--launcher", "subprocess", *FAKE)  # nothing left
    assert code == 0 and "nothing left to run" in out and [calls(r.cell_key) for r in rows] == [1, 1]
    code, out, _ = cli("sweep", "cancel", "-c", path, "--launcher", "subprocess")
    assert code == 0 and "no subprocess job of sweep t is queued or running" in out


@pytest.mark.parametrize("worker", [
    WorkerId("node7", 4242, "slurm", "812_3", "0"), WorkerId("node7", 4242), WorkerId("h.example", 1, gpu="GPU-3f"),
    WorkerId("n", 9, "subprocess", "77.0_1"),
])
def test_a_worker_id_reads_back_as_it_was_written(worker):
    assert WorkerId.parse(str(worker)) == worker


def test_the_worker_id_text_is_what_status_always_showed():
    assert str(WorkerId("node7", 4242, "slurm", "812_3", "0")) == "node7:4242 slurm 812_3 gpu0"
    assert WorkerId.parse("node7:4242 gpu0").job is None and WorkerId.parse(None) is None
    assert WorkerId.parse("not a worker id") is None


@pytest.mark.parametrize("args, message", [
    (["--gc", "--cancel"], "No such option: --gc"),  # the verbs are verbs, not flags of run
    (["run", "--dry-run"], "No such option: --dry-run"),
    (["gc", "--cancel"], "No such option: --cancel"),
    (["plan", "--retry-failed"], "No such option: --retry-failed"),
    (["cancel", "--workers", "2"], "No such option: --workers"),
    (["run", "--launcher", "local", "--detach"], "--detach: launcher local runs its workers in this command"),
    (["run", "--launcher", "slurm", "--workers", "2"], "--workers: options of the local launcher"),
    (["run", "--launcher", "pbs"], "--launcher pbs: must be one of local, slurm"),
    (["cancel", "--launcher", "local"], "--launcher local: its workers are the `sweep run` command's own"),
])
def test_combinations_that_make_no_sense_are_refused_in_one_line(cli, project, args, message):
    code, out, err = cli("sweep", *args, "-c", str(project.paths.base / "experiments.yaml"))
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1, (out, err)
    assert "Traceback" not in err


@pytest.mark.parametrize("verb, has, lacks", [
    ("run", ["--workers", "--launcher", "--detach", "--retry-failed", "--runner"], ["--gc", "--cancel", "--dry-run"]),
    ("plan", ["--only", "--workers"], ["--detach", "--retry-failed", "--launcher", "--runner", "--gc"]),
    ("gc", ["--dry-run", "--storage"], ["--workers", "--only", "--launcher", "--detach"]),
    ("cancel", ["--launcher", "--dry-run"], ["--workers", "--only", "--detach", "--retry-failed"]),
    ("status", ["--sweep", "--all", "--repair"], ["--workers", "--launcher", "--dry-run"]),
])
def test_each_verbs_help_lists_only_its_options(cli, verb, has, lacks):
    code, out, _ = cli("sweep", verb, "--help")
    options = set(re.findall(r"(--[a-z][a-z-]*)", out))
    assert code == 0 and set(has) <= options and not set(lacks) & options, options


def test_sweep_alone_is_run(cli, project, fake_dir):
    code, out, err = cli("sweep", "-c", str(project.paths.base / "experiments.yaml"), "--workers", "1", *FAKE)
    assert code == 0 and "done 2/2" in out, out + err


def test_a_cancel_is_recorded_so_the_watcher_stops_and_a_later_run_resumes(cli, project, fake_dir, tmp_path):
    """Issue 37, item 2: `sweep cancel` while a submitter watches in another shell: the watcher submits nothing
    again and exits, the sweep's parent run ends KILLED; a later explicit `sweep run` un-cancels and finishes each
    cell exactly once (their runs resumed, not repeated)."""
    import os
    import subprocess
    import sys
    import time

    from bronchocli.runs.client import client_for, experiment_id
    from bronchocli.runs.parents import KIND_SWEEP, find_parent
    from bronchocli.sweep.summary import TAG_CANCELLED

    kind = "subprocess_launcher:SubprocessLauncher"  # how a launcher outside the package is named
    path = str(project.paths.base / "experiments.yaml")
    for arch in ("baseline", "lstm"):
        (fake_dir / f"block-{arch}").write_text("")
    main = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), "COLUMNS": "200"}
    watcher = subprocess.Popen([sys.executable, "-c", main, "sweep", "run", "-c", path, "--launcher", kind, *FAKE],
                               cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    end = time.monotonic() + 300  # an event the test waits for (both cells running); the limit guards a hang
    while len(list(fake_dir.glob("started-*"))) < 2:
        assert watcher.poll() is None and time.monotonic() < end, watcher.stdout.read()
        time.sleep(0.05)
    code, out, err = cli("sweep", "cancel", "-c", path, "--launcher", kind)
    assert code == 0 and "cancelled subprocess job(s)" in out, out + err
    out, _ = watcher.communicate(timeout=300)
    assert watcher.returncode == 130 and "was cancelled" in out, out
    assert len(re.findall(r"submitted subprocess job", out)) == 1, out  # nothing submitted again
    client = client_for(project)
    parent = client.get_run(find_parent(client, experiment_id(client, project), KIND_SWEEP, project.name))
    assert parent.info.status == "KILLED" and TAG_CANCELLED in parent.data.tags
    rows = SweepStore(project.paths.storage_url).rows(project.name)
    assert {r.state for r in rows} == {"pending"}  # the stopped workers gave their cells back

    (fake_dir / "release").write_text("")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", kind, *FAKE)
    assert code == 0, out + err
    parent = client.get_run(parent.info.run_id)
    assert parent.info.status == "FINISHED" and TAG_CANCELLED not in parent.data.tags
    rows = SweepStore(project.paths.storage_url).rows(project.name)
    assert {r.state for r in rows} == {FINISHED} and runs_by_cell(project) == {r.cell_key: 1 for r in rows}


def test_the_launcher_names_have_one_owner_the_registry(cli, project):
    """``sweep.launcher`` is a plain name in the config (the config package cannot see the launchers); `config` and
    the sweep check it against the registry, so a registered launcher is a valid value with no other change."""
    import subprocess_launcher  # noqa: F401 - registers "subprocess"

    path = str(project.paths.base / "experiments.yaml")
    code, out, err = cli("config", "-c", path, "--set", "sweep.launcher=PBS")
    assert code == 2 and err.strip() == f"error: sweep.launcher pbs: must be one of {', '.join(names())}", err
    code, out, err = cli("config", "-c", path, "--set", "sweep.launcher=Subprocess")
    assert code == 0 and "launcher: subprocess" in out, err


def _install_entry_point(site):
    """A distribution in ``site`` (what pip installs: a ``.dist-info`` folder) whose entry point of the group
    ``bronchopose.launchers`` offers subprocess_launcher's class as the launcher ``subprocess``."""
    dist = site / "subprocess_launcher_plugin-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: subprocess-launcher-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[bronchopose.launchers]\n"
                                           "subprocess = subprocess_launcher:SubprocessLauncher\n")
    return site


def test_a_launcher_installed_through_an_entry_point_runs_a_sweep_with_its_own_validated_section(
        make_config, project, fake_dir, tmp_path):
    """Issue 47, item 2: a package adds a launcher without touching this repository (an entry point of the group
    ``bronchopose.launchers``); its settings are its own section, ``sweep.launchers.<name>``, validated by its own
    model when it is looked up. Run in fresh processes: nothing here imports or registers the launcher."""
    import os
    import subprocess
    import sys

    from sweep_fakes import FAKE

    site = _install_entry_point(tmp_path / "site")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), *sys.path]), "COLUMNS": "200"}
    probe = ("import sys; from bronchocli.sweep.launchers import launcher_class, names; "
             "print('subprocess_launcher' in sys.modules, 'subprocess' in names()); "
             "k = launcher_class('subprocess'); print(k.__module__, k.__name__, k.Settings.__name__)")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "True", "subprocess_launcher", "SubprocessLauncher", "SubprocessSettings"], out

    main = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"

    def bronchopose(*args):
        done = subprocess.run([sys.executable, "-c", main, *args], cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=300)
        return done.returncode, done.stdout, done.stderr

    cfg = make_config(sweep={"launchers": {"subprocess": {"max_workers": 1}}})
    path = str(cfg.paths.base / "experiments.yaml")
    code, out, err = bronchopose("sweep", "run", "-c", path, "--launcher", "subprocess", *FAKE)
    assert code == 0, out + err
    assert re.search(r"submitted subprocess job \S+: 1 worker\(s\) for stage grid", out), out  # max_workers: 1
    rows = SweepStore(cfg.paths.storage_url).rows(cfg.name)
    assert {r.state for r in rows} == {FINISHED} and [calls(r.cell_key) for r in rows] == [1, 1]
    workers = {WorkerId.parse(r.worker).job for r in rows}  # one worker, its job id from its environment
    assert len(workers) == 1 and None not in workers, [r.worker for r in rows]

    code, out, err = bronchopose("config", "-c", path, "--set", "sweep.launchers.subprocesss.max_workers=2")
    assert code == 2 and "sweep.launchers.subprocesss: no launcher of that name (known: local, slurm, subprocess" \
        in err, err
    make_config(sweep={"launchers": {"subprocess": {"max_workers": 0}}})  # the same file, a bad value
    for args in (["config"], ["sweep", "run", "--launcher", "subprocess", *FAKE]):
        code, out, err = bronchopose(*args, "-c", path)
        assert code == 2 and len(err.strip().splitlines()) == 1, (args, out, err)
        assert ("sweep.launchers.subprocess.max_workers: 0: input should be greater than or equal to 1 (allowed "
                "range [1, 64])") in err, err


def test_detected_asks_launchers_that_only_an_entry_point_offers(tmp_path):
    """Issue 58, item 4: inside a job of a launcher that an installed package offers (nothing imported it yet),
    ``detected()`` finds that launcher's environment, as it finds Slurm's inside a Slurm job; outside, none."""
    import os
    import subprocess
    import sys

    from subprocess_launcher import JOB_ENV

    site = _install_entry_point(tmp_path / "site")
    probe = "from bronchocli.sweep.launchers import detected; e = detected(); print(e and e.__name__)"
    env = {k: v for k, v in os.environ.items() if k not in ("SLURM_JOB_ID", JOB_ENV)}
    env["PYTHONPATH"] = os.pathsep.join([str(site), *sys.path])
    outside = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True)
    inside = subprocess.run([sys.executable, "-c", probe], env={**env, JOB_ENV: "77_0"}, capture_output=True,
                            text=True, check=True)
    assert (outside.stdout.strip(), inside.stdout.strip()) == ("None", "SubprocessEnvironment"), (outside, inside)


def test_a_plugin_whose_import_raises_is_one_line_naming_it_and_debug_shows_the_traceback(project, tmp_path):
    """Issue 60, item 2: any exception while loading a launcher plugin (here RuntimeError at import) is one line
    naming the entry point, its module, the exception's type and message, exit 2; ``--debug`` adds the
    traceback. Another launcher's option error does not trip over the broken one."""
    import os
    import subprocess
    import sys

    site = tmp_path / "site"
    dist = site / "broken_plugin-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[bronchopose.launchers]\nbroken = broken_launcher:BrokenLauncher\n")
    (site / "broken_launcher.py").write_text("raise RuntimeError('cluster config /etc/pbs.conf missing')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), *sys.path]), "COLUMNS": "300"}
    main = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
    path = str(project.paths.base / "experiments.yaml")

    def bronchopose(*args):
        done = subprocess.run([sys.executable, "-c", main, *args], cwd=tmp_path, env=env, capture_output=True,
                              text=True, timeout=300)
        return done.returncode, done.stdout, done.stderr

    line = ("error: sweep.launcher broken: entry point broken = broken_launcher:BrokenLauncher (group "
            "bronchopose.launchers) cannot be loaded: RuntimeError: cluster config /etc/pbs.conf missing; "
            "`bronchopose --debug ...` shows its traceback")
    code, out, err = bronchopose("sweep", "plan", "-c", path, "--set", "sweep.launcher=broken")
    assert (code, err.strip()) == (2, line), (out, err)
    code, out, err = bronchopose("--debug", "sweep", "plan", "-c", path, "--set", "sweep.launcher=broken")
    assert code == 2 and err.startswith(line + "\n") and "Traceback (most recent call last)" in err
    assert 'broken_launcher.py", line 1' in err, err
    code, out, err = bronchopose("sweep", "run", "-c", path, "--launcher", "slurm", "--workers", "2")
    assert code == 2 and "broken" not in err and "--workers: options of the local" in err, err


def test_a_launcher_whose_submission_raises_ends_the_sweeps_parent_run_failed_with_the_reason(
        cli, project, fake_dir, monkeypatch):
    """Issue 60, item 2: a plugin's ``submit()`` failing is one line naming the launcher and the error, and the
    sweep's parent run ends FAILED saying why (never left RUNNING)."""
    import subprocess_launcher

    from bronchocli.runs.client import client_for, experiment_id
    from bronchocli.runs.parents import KIND_SWEEP, find_parent
    from bronchocli.runs.records import TAG_FAILURE

    def refused(self, n, stage, after=()):
        raise RuntimeError("qsub: queue gpu does not exist\nmore detail")

    monkeypatch.setattr(subprocess_launcher.SubprocessLauncher, "submit", refused)
    path = str(project.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", "subprocess", *FAKE)
    reason = "RuntimeError: qsub: queue gpu does not exist"
    assert code == 2 and err.strip() == (f"error: launcher subprocess: submitting 2 worker(s) for stage grid failed: "
                                         f"{reason}; `bronchopose --debug ...` shows its traceback"), err
    client = client_for(project)
    parent = client.get_run(find_parent(client, experiment_id(client, project), KIND_SWEEP, project.name))
    assert parent.info.status == "FAILED" and reason in parent.data.tags[TAG_FAILURE]


def test_a_cancel_touches_only_what_runs_and_names_a_study_that_is_not_there(cli, project, fake_dir):
    """Issue 60, item 5: `sweep cancel` of a finished sweep leaves its FINISHED parent run FINISHED (not KILLED,
    not tagged cancelled); `sweep cancel --study nosuch` fails in one line saying there is no such study."""
    from bronchocli.runs.client import client_for, experiment_id
    from bronchocli.runs.parents import KIND_SWEEP, find_parent
    from bronchocli.sweep.summary import TAG_CANCELLED

    kind = "subprocess_launcher:SubprocessLauncher"  # a launcher whose workers `sweep cancel` stops
    path = str(project.paths.base / "experiments.yaml")
    code, out, err = cli("sweep", "run", "-c", path, "--launcher", kind, *FAKE)
    assert code == 0, out + err
    client = client_for(project)
    parent = find_parent(client, experiment_id(client, project), KIND_SWEEP, project.name)
    assert client.get_run(parent).info.status == "FINISHED"
    code, out, err = cli("sweep", "cancel", "-c", path, "--launcher", kind)
    assert code == 0, out + err
    run = client.get_run(parent)
    assert run.info.status == "FINISHED" and TAG_CANCELLED not in run.data.tags
    code, out, err = cli("sweep", "cancel", "-c", path, "--study", "nosuch", "--launcher", kind)
    assert code == 2 and err.strip().startswith("error: sweep cancel --study nosuch: no such study (no parent run "
                                                "of it in experiment"), err
    assert len(err.strip().splitlines()) == 1


def test_sweep_run_checks_the_launcher_and_the_storage_once(make_config, monkeypatch):
    """Issue 58.3: ``launcher.check()`` (Slurm: ``sbatch --test-only``) and the storage's answer are asked once per
    ``sweep run``, before anything is created, not again by the driver."""
    from rich.console import Console
    from subprocess_launcher import SubprocessLauncher

    from bronchocli.sweep import entry, launch
    from bronchocli.sweep.storage import SweepStore
    from bronchocli.sweep.task import TaskSpec

    calls: list[str] = []
    exists = SweepStore.exists
    monkeypatch.setattr(SubprocessLauncher, "check", lambda self: calls.append("check"))
    monkeypatch.setattr(SweepStore, "exists", lambda self: calls.append("exists") or exists(self))

    class Prepared(Exception):
        """The driver began preparing the sweep's shared state: every check is behind it."""

    def prepare(*args, **kwargs):
        calls.append("prepare")
        raise Prepared

    monkeypatch.setattr(launch, "prepare_walk", prepare)
    cfg = make_config()
    spec = TaskSpec(config=str(cfg.paths.base / "experiments.yaml"))
    with pytest.raises(Prepared):
        entry.run(cfg, spec, SubprocessLauncher, detach=True, console=Console(quiet=True))
    assert calls == ["check", "exists", "prepare"]  # the driver checks nothing again
