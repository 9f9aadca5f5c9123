"""Shared fixtures: the repository root and a CLI runner that checks exit codes; each test process's own claims folder.

The suite runs in parallel under pytest-xdist (``-n 2``, ``--dist loadgroup``): every worker is a process of its
own with its own core-claims folder (``pytest_configure``); tests that share one external resource for the
session (the real Slurm cluster of tests/sweep/test_slurm.py) carry ``xdist_group`` so one worker runs them all.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest
from mounts import tmpfs

REPO = Path(__file__).resolve().parents[1]
# The CT-derived tree of the Chaste project (BSD-3, licence beside it), kept in the repository so a clean checkout anywhere runs the real-anatomy tests.
REAL_TREE = REPO / "tests" / "fixtures" / "airways" / "TestSubject002MajorAirways.vtu"

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("MPLBACKEND", "Agg")
# torch's OpenMP threads sleep while they wait for work instead of spinning (GNU OpenMP's default spins first):
# with two xdist workers on two cores, a torch process of two threads (a training that takes its share, a
# report, the CLI's in-process commands) shares its cores with the other worker, and a thread spinning at a
# barrier for a descheduled peer burns the other worker's CPU: the 7 round-trip and detach tests of
# tests/models/test_architectures.py took 107 CPU-s spinning on a shared core, 12.5 sleeping. Set before torch loads
# (its OpenMP reads it then); the workers and every process a test starts inherit it. Thread counts, what each
# thread computes and so the numbers are unchanged.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
if "PYTEST_XDIST_WORKER" in os.environ:
    # pytest-xdist starts its workers with COLUMNS=80; the CLI's consoles (commands/common.py), made at import,
    # would keep that width and wrap the lines the tests read, whatever width a test's command asks for.
    os.environ.pop("COLUMNS", None)
    os.environ.pop("LINES", None)
_RUNTIME: Path | None = None  # this test process's XDG_RUNTIME_DIR (pytest_configure)
_PYCACHE: Path | None = None  # a compiled-modules folder made for this session only (no pytest cache folder)


def _compile_each_module_once(config) -> None:
    """Under ``PYTHONDONTWRITEBYTECODE``, let the suite's processes share one folder of compiled modules.

    With the variable set (some machines set it for every shell) no process writes a ``.pyc``, so every Python
    process the suite starts (xdist workers, CLI subprocesses, sweep and tune workers, Slurm tasks, UI servers)
    compiles from source all it imports wherever the environment has no ``.pyc`` (an editable checkout; a venv
    installed without byte compilation, as uv does by default): about 3.5 s more CPU per ``import torch, mlflow``
    on the 2-core machine (benchmarks/README.md), in hundreds of processes. Here the variable is dropped for this
    process and every process started after it, and ``PYTHONPYCACHEPREFIX`` sends the ``.pyc`` files to the pytest
    cache folder (``.pytest_cache/d/pycache``), never beside the sources: each module is compiled once, then read.
    Only how Python caches compiled code changes; what runs is the same. Without the variable nothing changes."""
    global _PYCACHE
    if not (sys.flags.dont_write_bytecode or os.environ.get("PYTHONDONTWRITEBYTECODE")):
        return
    if os.environ.get("PYTHONPYCACHEPREFIX"):  # the user's own prefix: keep it
        folder = Path(os.environ["PYTHONPYCACHEPREFIX"])
    elif getattr(config, "cache", None) is not None:
        folder = config.cache.mkdir("pycache")
    else:  # -p no:cacheprovider
        folder = _PYCACHE = Path(tempfile.mkdtemp(prefix="bronchopose-tests-pycache-"))
    folder = folder.resolve()
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    os.environ["PYTHONPYCACHEPREFIX"] = str(folder)
    sys.dont_write_bytecode = False  # this process: importlib reads both at every import
    sys.pycache_prefix = str(folder)


def pytest_configure(config):
    """Give this test process (an xdist worker, or the single pytest process) a runtime folder of its own.

    Training processes share the machine's cores through claims in ``$XDG_RUNTIME_DIR/bronchopose/cores``
    (bronchocli/runs/cores.py). A shared folder would let one worker's training, or the user's own run on the
    machine, change the threads another test's training decides: each process gets an empty one, and the
    processes a test starts inherit it. Tests about the sharing itself set their own (test_shared_cores.py)."""
    global _RUNTIME
    _compile_each_module_once(config)  # before pytest-xdist starts its workers: they inherit the environment
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    _RUNTIME = Path(tempfile.mkdtemp(prefix=f"bronchopose-tests-{worker}-"))
    os.environ["XDG_RUNTIME_DIR"] = str(_RUNTIME)


def pytest_collection_finish(session):
    """Under pytest-xdist, a worker's torch takes its share of the cores (cores / workers threads), not all of them.

    torch's default is every core, in each worker: two workers on two cores ran four compute threads whose
    OpenMP teams spin-wait for each other (the oversubscription one_thread avoids for single tests). Training
    still sets the threads it decides (``runs.cores``, ``train.threads``), and processes a test starts keep
    torch's own default: only the tests' in-process torch work (models, inference, profiling) changes."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if "PYTEST_XDIST_WORKER" not in os.environ or workers < 2:
        return
    import torch  # collected test modules have mostly imported it already

    from bronchocli.runs.cores import machine_cores

    torch.set_num_threads(max(1, machine_cores() // workers))


def pytest_unconfigure(config):
    for folder in (_RUNTIME, _PYCACHE):  # a worker's _PYCACHE is None: the folder is the main process's
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


class _StoreTemplate:
    """An initialised, empty MLflow SQLite store, made at most once per test process (MLflow's migrations take
    seconds; a copy takes milliseconds) and only when a test first needs one."""

    def __init__(self, folder: Path):
        self.folder = folder
        self._path: Path | None = None

    def path(self) -> Path:
        if self._path is None:
            from mlflow.tracking import MlflowClient

            path = self.folder / "mlflow.db"
            MlflowClient(tracking_uri=f"sqlite:///{path}").search_experiments()
            self._path = path
        return self._path

    def seed(self, db: Path) -> None:
        """Copy the template to ``db`` (whose folder exists) unless a store is there; atomic (a rename)."""
        if db.exists() or not db.parent.is_dir():
            return
        part = db.with_name(f".{db.name}.template-{os.getpid()}")
        shutil.copyfile(self.path(), part)
        os.replace(part, db)


@pytest.fixture(scope="session")
def mlflow_store_template(tmp_path_factory) -> _StoreTemplate:
    return _StoreTemplate(tmp_path_factory.mktemp("mlflow-template"))


@pytest.fixture(scope="session")
def mlflow_template(mlflow_store_template) -> Path:
    """The template store's file, for tests that copy it into a project themselves (tests/sweep's configs)."""
    return mlflow_store_template.path()


@pytest.fixture(autouse=True, scope="session")
def _new_sqlite_stores_from_the_template(mlflow_store_template):
    """Every MLflow SQLite store a test's own process opens for the first time starts as a copy of the template.

    ``bronchocli.runs.client._open`` is where a ``runs.uri`` store is first opened (its tables created, under the
    store's file lock); an empty store copied there is the file MLflow's migrations would have written, in
    milliseconds instead of seconds. Processes a test starts (CLI subprocesses, sweep workers) still create
    their stores themselves, so MLflow's own creation stays under test there."""
    from bronchocli import urls
    from bronchocli.runs import client

    original = client._open

    def opened(uri: str):
        db = urls.sqlite_file(uri)
        if db is not None:
            mlflow_store_template.seed(db)
        return original(uri)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(client, "_open", opened)
        yield


@pytest.fixture
def one_thread():
    """Tiny inputs: one torch thread (a team of threads on a shared CPU is ten times slower here)."""
    import torch  # lazy: most tests never load torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def repo() -> Path:
    return REPO


@pytest.fixture
def real_tree() -> Path:
    assert REAL_TREE.is_file(), f"{REAL_TREE} is missing from the checkout"
    return REAL_TREE


@pytest.fixture
def cli(monkeypatch):
    """Run ``bronchocli.cli.main`` in-process, through the console script's own error and exit-code path.

    Returns (exit code, stdout, stderr). An exception that ``main`` lets through
    (a traceback for a user) fails the test.
    """
    from bronchocli.cli import main

    monkeypatch.setenv("COLUMNS", "200")
    monkeypatch.setenv("NO_COLOR", "1")

    def run(*args: str) -> tuple[int, str, str]:
        out, err = io.StringIO(), io.StringIO()
        code = 0
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main([str(a) for a in args])
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        return code, out.getvalue(), err.getvalue()

    return run


@pytest.fixture
def small_fs(tmp_path):
    """A 1 MB tmpfs mounted at ``tmp_path/small``."""
    with tmpfs(tmp_path / "small", "1m") as mount:
        yield mount


SERVICES = ("slurm", "postgres", "browser")  # the markers of tests that need a real service
# heavy (left out of the fast tier): the modules whose tests took more than 1.5 s each on average, or one of them
# more than 20 s, in the measured xdist runs (benchmarks/results/test-durations-after.txt: a shared 2-core machine,
# about ten times its idle times), and tests/training (every module trains or starts a process)
HEAVY_FOLDERS = ("tests/training/",)
HEAVY_MODULES = frozenset(f"tests/{m}.py" for m in """
    anatomy/test_surface data/test_cache data/test_importer_canonical diagnostics/test_selftest
    generation/test_generate_cli generation/test_pipeline inference/test_api_doc inference/test_mlflow_model
    inference/test_portable_model inference/test_track models/test_architectures models/test_imagenet_weights
    models/test_pretrained models/test_profile models/test_weights_install render/test_camera render/test_real_tree
    render/test_scene render/test_worker_lifetime reporting/test_best reporting/test_calibration
    reporting/test_config_tie reporting/test_figures reporting/test_frames_and_curves reporting/test_latex
    reporting/test_report_atomic reporting/test_report_cli reporting/test_report_real reporting/test_training_curves
    sweep/test_busy sweep/test_commands sweep/test_disk_full sweep/test_dry_runs sweep/test_fresh_postgres
    sweep/test_housekeeping sweep/test_launchers sweep/test_one_database sweep/test_parent_tags_race
    sweep/test_placement sweep/test_processes sweep/test_real_sweep sweep/test_record sweep/test_report_running
    sweep/test_slurm sweep/test_slurm_faults sweep/test_stages sweep/test_tuning sweep/test_worker test_cli test_extras
    test_relocation test_run_processes test_ui
""".split())  # and, in test_bad_inputs.py (fast on average), its few costly tests, marked there
POSTGRES_FIXTURES = {"pg_url", "fresh_db"}  # tests/sweep/conftest.py: a schema or a database of the local server


def _root_id(config) -> str:
    """The node id of this folder (the base id of this conftest's fixtures)."""
    return Path(os.path.relpath(Path(__file__).parent, config.rootpath)).as_posix()


def _shared_fixture_group(item) -> str | None:
    """The xdist group of a test that uses a costly fixture built once for several tests: its module for a
    module- or class-scoped one, the defining folder for a session-scoped one of a sub-folder's conftest.py
    (the root conftest's session fixtures are cheap: every worker makes its own)."""
    info = getattr(item, "_fixtureinfo", None)  # pytest's record of the test's fixtures
    if info is None:
        return None
    folders, module = [], None
    for defs in info.name2fixturedefs.values():
        fixture = defs[-1]
        scope = str(getattr(fixture.scope, "value", fixture.scope))
        if scope in ("session", "package"):
            # not the root conftest's or a plugin's (the template store, tmp_path_factory): every test reaches
            # those through the autouse store fixture, and they grouped every test with its module (so the
            # longest modules of one or two tests went last, as xdist hands out groups of fewer tests later)
            if fixture.baseid not in ("", _root_id(item.config)):
                folders.append(fixture.baseid)
        elif scope != "function":
            module = item.nodeid.split("::")[0]
    # the widest place: every test of a folder whose session fixture one of them uses shares one worker
    return min(folders, key=lambda b: (b.count("/"), b)) if folders else module


def _longest_first(items: list) -> list:
    """Under pytest-xdist: the tests of no group ordered service tests first, then the other ``heavy`` ones, then
    the rest (stable: a module's order is kept within each class).

    ``--dist loadgroup`` hands out the groups first (largest first), then the tests of no group one at a time in
    collection order, to whichever worker runs short. In plain collection order tests/training and the root's
    process and server tests (20-50 s each on the idle 2-core machine) came last, so one worker could end with
    a long test while the other had nothing left: the longest-first order ends both on short tests. Grouped
    tests keep their places (their fixtures are shared in the group's order); every worker collects the same
    order, as xdist requires."""
    def weight(item) -> int:
        if item.get_closest_marker("xdist_group") is not None:
            return 2
        if any(item.get_closest_marker(m) for m in SERVICES):
            return 0
        return 1 if item.get_closest_marker("heavy") else 2

    return sorted(items, key=weight)


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's worker reads the xdist_group marks into the node ids
def pytest_collection_modifyitems(config, items):
    """Tests sharing a module- or folder-wide fixture run on one xdist worker (``--dist loadgroup``), so the
    fixture (a trained run, a finished sweep and its UI server, a browser) is built once, not once per worker.

    A test that needs a service is ``heavy`` (the fast tier, ``-m "not slow and not heavy"``, leaves it out);
    one that uses the local PostgreSQL through tests/sweep's fixtures is ``postgres``.

    ``gpu`` tests run where CUDA exists and are skipped with the reason elsewhere."""
    for item in items:
        if POSTGRES_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.postgres)
        module = item.nodeid.split("::")[0]
        if (any(item.get_closest_marker(m) for m in SERVICES) or module in HEAVY_MODULES
                or module.startswith(HEAVY_FOLDERS)):
            item.add_marker(pytest.mark.heavy)
        if item.get_closest_marker("xdist_group") is None:
            group = _shared_fixture_group(item)
            if group is not None:
                item.add_marker(pytest.mark.xdist_group(group))
    if "PYTEST_XDIST_WORKER" in os.environ:
        items[:] = _longest_first(items)
    # The marker, not ``item.keywords``: keywords hold every parent node's name, so a checkout in a folder
    # named ``gpu`` would skip the whole suite.
    if not any(item.get_closest_marker("gpu") for item in items):
        return
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (run `pytest -m gpu` in a GPU session)")
    for item in items:
        if item.get_closest_marker("gpu"):
            item.add_marker(skip)
