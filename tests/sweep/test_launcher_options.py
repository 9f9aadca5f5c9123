"""Launcher options as one declared mapping (issue 58, item 1): ``Launcher.parameters`` (name -> ``Parameter``),
checked when a launcher is registered; the command line's flags generated from every installed launcher's
parameters; the documented example launcher (docs/examples/ssh_launcher.py) installed through an entry point."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from sweep_fakes import FAKE, calls
from tinydata import write_tiny_dataset

from bronchocli.errors import BronchoError
from bronchocli.sweep import FINISHED, SweepStore
from bronchocli.sweep import launchers
from bronchocli.sweep.entry import launcher_options
from bronchocli.sweep.launchers import GENERIC, Job, Launcher, LocalLauncher, Parameter, SlurmLauncher, register

EXAMPLES = Path(__file__).resolve().parents[2] / "docs" / "examples"
MAIN = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"


@pytest.fixture
def registry(monkeypatch):
    """The launchers' registry, restored afterwards (a test's registrations do not reach the others)."""
    monkeypatch.setattr(launchers, "_LAUNCHERS", dict(launchers._LAUNCHERS))


def _launcher(name: str, parameters: dict) -> type[Launcher]:
    class ProbeJob(Job):
        cancel = lambda self: None  # noqa: E731

    class Probe(Launcher):
        submit = active = describe = lambda self, *a, **k: None  # noqa: E731
        Job = ProbeJob

    Probe.name, Probe.parameters = name, parameters
    return Probe


@pytest.mark.parametrize("name, parameters, line", [
    ("pbs", {"hosts": Parameter(list)}, "launcher pbs: parameter 'hosts': must be generic (workers, gpus, per_gpu) "
                                        "or the launcher's own, pbs_<option> (lower case, e.g. pbs_hosts)"),
    ("pbs", {"ssh_hosts": Parameter(list)}, "launcher pbs: parameter 'ssh_hosts': must be generic"),
    ("pbs", {"pbs_Queue": Parameter(str)}, "launcher pbs: parameter 'pbs_Queue': must be generic"),
    ("pbs", {"workers": Parameter(str)}, "launcher pbs: parameter 'workers': a generic parameter is declared as "
                                         "launchers.GENERIC has it"),
    ("pbs", {"pbs_queue": "--queue"}, "launcher pbs: parameter 'pbs_queue': must be a Parameter of type int"),
    ("pbs", ("--workers",), "launcher pbs: parameters must be a mapping of name -> Parameter, not tuple"),
])
def test_a_parameter_name_neither_generic_nor_prefixed_is_refused_at_registration(registry, name, parameters, line):
    with pytest.raises(BronchoError) as refused:
        register(_launcher(name, parameters))
    assert str(refused.value).startswith(line) and "\n" not in str(refused.value), str(refused.value)
    assert name not in launchers.names()


def test_generic_and_prefixed_parameters_are_registered(registry):
    kind = register(_launcher("pbs", {"workers": GENERIC["workers"], "pbs_queue": Parameter(str, "Queue.")}))
    assert launchers.launcher_class("pbs") is kind
    assert list(launchers.parameters()) == ["workers", "gpus", "per_gpu", "pbs_queue"]  # generic ones once, first
    assert LocalLauncher.parameters == GENERIC and SlurmLauncher.parameters == {}


def test_an_option_the_launcher_does_not_take_is_refused_in_one_line_naming_the_launchers_that_do(registry):
    register(_launcher("pbs", {"pbs_queue": Parameter(str, choices=("gpu", "cpu"))}))
    with pytest.raises(BronchoError, match=r"^--pbs-queue: options of the pbs launcher; launcher slurm does not "
                                           r"take it \(docs/sweep.md"):
        launcher_options(SlurmLauncher, {"pbs_queue": "gpu", "workers": None})  # None: not given
    with pytest.raises(BronchoError, match=r"^--per-gpu, --pbs-queue: options of the local/pbs launcher;"):
        launcher_options(SlurmLauncher, {"per_gpu": 2, "pbs_queue": "gpu"})
    with pytest.raises(BronchoError, match=r"^--sge-queue: no installed launcher takes it \(launcher options: "
                                           r"--workers, --gpus, --per-gpu, --pbs-queue\)"):
        launcher_options(SlurmLauncher, {"sge_queue": "gpu"})
    pbs = launchers.launcher_class("pbs")
    with pytest.raises(BronchoError, match=r"^api.sweep: pbs_queue='x': must be one of gpu, cpu \(as --pbs-queue"):
        launcher_options(pbs, {"pbs_queue": "x"})
    assert launcher_options(pbs, {"pbs_queue": "cpu"}) == {"pbs_queue": "cpu"}


def _install(site: Path, entries: str, name: str = "plugins") -> dict[str, str]:
    """A distribution in ``site`` declaring ``entries`` in the group ``bronchopose.launchers``; the environment of a
    fresh process that sees it, and the example launcher's module."""
    dist = site / f"{name}-0.1.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[bronchopose.launchers]\n{entries}")
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(EXAMPLES), *sys.path]), "COLUMNS": "200"}


def _bronchopose(env, cwd, *args):
    done = subprocess.run([sys.executable, "-c", MAIN, *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)
    return done.returncode, done.stdout, done.stderr


def test_an_entry_point_launchers_parameter_is_a_flag_of_sweep_run(make_config, tmp_path):
    """``--ssh-hosts`` appears in ``sweep run --help`` once the example launcher's entry point is installed (a
    broken plugin beside it is left out of the help); other launchers refuse it, naming ssh."""
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "broken_launcher.py").write_text("raise RuntimeError('no cluster here')\n")
    env = _install(tmp_path / "site", "ssh = ssh_launcher:SshLauncher\nbroken = broken_launcher:BrokenLauncher\n")
    code, out, err = _bronchopose(env, tmp_path, "sweep", "run", "--help")
    assert code == 0 and "broken" not in out + err, out + err
    flags = re.findall(r"(--[a-z][a-z-]*)", out)
    assert "--ssh-hosts" in flags and flags.count("--workers") == 1, flags
    assert "localhost: a worker started here without ssh" in out
    path = str(make_config().paths.base / "experiments.yaml")
    code, out, err = _bronchopose(env, tmp_path, "sweep", "run", "-c", path, "--launcher", "local", "--ssh-hosts",
                                  "a,b")
    assert code == 2 and err.strip().startswith("error: --ssh-hosts: options of the ssh launcher; launcher local "
                                                "does not take it"), err
    assert len(err.strip().splitlines()) == 1
    code, out, _ = _bronchopose({**env, "PYTHONPATH": os.pathsep.join(sys.path)}, tmp_path, "sweep", "run", "--help")
    assert code == 0 and "--ssh-hosts" not in out and "--workers" in out


def test_the_example_ssh_launcher_runs_a_two_cell_sweep_on_localhost(make_config, fake_dir, tmp_path):
    """The documented example, installed through an entry point, runs a sweep's cells on ``--ssh-hosts localhost``
    (its workers started here, no ssh): each cell once, FINISHED; ``--workers`` is refused with it."""
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    cfg = make_config()
    path = str(cfg.paths.base / "experiments.yaml")
    env = _install(tmp_path / "site", "ssh = ssh_launcher:SshLauncher\n")
    code, out, err = _bronchopose(env, tmp_path, "sweep", "run", "-c", path, "--launcher", "ssh", "--ssh-hosts",
                                  "localhost,localhost", *FAKE)
    assert code == 0, out + err
    assert re.search(r"submitted ssh job \S+: 2 worker\(s\) for stage grid", out), out
    rows = SweepStore(cfg.paths.storage_url).rows(cfg.name)
    assert len(rows) == 2 and {r.state for r in rows} == {FINISHED}
    assert [calls(r.cell_key) for r in rows] == [1, 1]
    code, out, err = _bronchopose(env, tmp_path, "sweep", "run", "-c", path, "--launcher", "ssh", "-w", "2", *FAKE)
    assert code == 2 and "--workers: options of the local launcher; launcher ssh does not take it" in err, err
