"""A catalogue of bad inputs: every one gives its exit code and one line naming the culprit, no traceback,
nothing half-written; and property tests of the config loader and of `--set` parsing.

Each catalogue entry builds its bad input in a fresh project (a tiny dataset and a valid experiments.yaml on
SQLite stores) and runs the command in-process through the console script's own error path (`cli`).
"""

from __future__ import annotations

import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tinydata import write_tiny_dataset

from bronchocli import urls
from bronchocli.config import Config, load_config, parse_override
from bronchocli.errors import ConfigError, OutOfMemory, out_of_memory
from bronchocli.generation import ensure_dataset

REPO = Path(__file__).resolve().parents[1]
TINY_GENERATE = ["--set", "dataset.generate.max_frames=3", "--set", "dataset.generate.voxel_mm=1.0",
                 "--set", "dataset.generate.lobes=[br]", "--patients", "1", "--trajectories", "1",
                 "--image-size", "16", "--workers", "1", "--no-progress"]


@dataclass
class Project:
    root: Path
    config: Path
    silent_port: int  # a TCP port that accepts connections and never answers (a hung server)
    mounts: list[Path] = field(default_factory=list)  # file systems a case mounted (unmounted afterwards)

    def write(self, name: str, text: str | bytes) -> Path:
        path = self.root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        return path

    def files(self) -> set[str]:
        return {str(p.relative_to(self.root)) for p in self.root.rglob("*")}


@pytest.fixture
def silent_port():
    """A listening socket nobody accepts on: connections succeed and then hear nothing, like a hung server."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(64)
        yield s.getsockname()[1]


@pytest.fixture
def project(tmp_path, silent_port):
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    config = tmp_path / "experiments.yaml"
    config.write_text(yaml.safe_dump({
        "name": "bad", "dataset": {"root": "data/tiny"},
        "grid": {"arch": ["baseline"], "rot_loss": ["mse"], "population": ["personalized"], "seed": [0]},
        "runs": {"timeout_s": 1}, "train": {"steps": 2, "batch_size": 2, "threads": 1},
    }))
    project = Project(tmp_path, config, silent_port)
    yield project
    for mount in project.mounts:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def edit_csv_row(p: Project) -> Path:
    csv = p.root / "data" / "tiny" / "p00.csv"
    lines = csv.read_text().splitlines()
    lines[3] = "p00,ur,0,zz," + ",".join(lines[3].split(",")[4:])  # a frame number that is not a number
    csv.write_text("\n".join(lines) + "\n")
    return csv


def C(p: Project) -> list[str]:
    return ["-c", str(p.config)]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def hung(p: Project, scheme: str = "http") -> str:
    return f"{scheme}://bob:hunter2@127.0.0.1:{p.silent_port}" + ("/db" if scheme == "postgresql" else "")


# id -> (make the bad input and return the argv, exit code, text the one line must contain)
CATALOGUE: dict[str, tuple[Callable[[Project], list[str]], int, str]] = {
    # -- the config file -------------------------------------------------------------
    "malformed YAML": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: t\ngrid: [\n"))], 2,
                       "e.yaml:3: YAML syntax error"),
    "duplicate key": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: t\ntrain:\n  lr: 1\n  lr: 2\n"))],
                      2, "e.yaml:4: duplicate key 'lr' (first written at line 3)"),
    "non-UTF-8 file": (lambda p: ["config", "-c", str(p.write("e.yaml", b"name: t\n# caf\xe9\n"))], 2,
                       "e.yaml:2: not UTF-8 text"),
    "not a mapping": (lambda p: ["config", "-c", str(p.write("e.yaml", "- a\n- b\n"))], 2,
                      "expected a mapping of sections"),
    "missing config file": (lambda p: ["config", "-c", str(p.root / "nope.yaml")], 2, "nope.yaml: config file not found"),
    "config is a folder": (lambda p: ["config", "-c", str(p.root / "data")], 2, "config file not found"),
    "unknown key": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: t\ntrain: {colour: red}\n"))], 2,
                    "e.yaml:2: train.colour: unknown key 'colour'"),
    "unknown architecture": (lambda p: ["config", *C(p), "--set", "grid.arch=[transformer]"], 2, "grid.arch[0]"),
    "empty grid axis": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: t\ngrid:\n  arch: []\n"))], 2,
                        "e.yaml:3: grid.arch: []: value error, must list at least one value"),
    "negative size": (lambda p: ["config", *C(p), "--set", "train.batch_size=-4"], 2,
                      "--set train.batch_size=-4: train.batch_size: -4: input should be greater than or equal to 1"),
    "negative timeout": (lambda p: ["config", *C(p), "--set", "runs.timeout_s=-1"], 2, "runs.timeout_s"),
    "unknown profile": (lambda p: ["config", *C(p), "--profile", "nosuch"], 2, "no such profile"),
    "--set without =": (lambda p: ["config", *C(p), "--set", "trainlr"], 2, "expected key.path=value"),
    "--set of an unknown section": (lambda p: ["config", *C(p), "--set", "foo.bar.baz=1"], 2,
                                    "--set foo.bar.baz=1: foo: unknown key 'foo'"),
    "--set into a value": (lambda p: ["config", *C(p), "--set", "name.x=1"], 2, "'name' in 'name.x' is a value"),
    "--set grid.* that every stage overrides": (
        lambda p: ["config", *C(p), "--set", "stages=[{name: a, grid: {arch: [lstm]}}]", "--set", "grid.arch=[conv3d]"],
        2, "--set grid.arch=[conv3d]: has no effect: the stages decide the cells and every stage sets arch itself"),
    "password in a bad value": (lambda p: ["config", *C(p), "--set", "storage.url=[postgresql://u:hunter2@h/db]"],
                                2, "postgresql://u:***@h/db"),
    # -- flags -------------------------------------------------------------------------
    "tune --trials 0": (lambda p: ["tune", *C(p), "-a", "lstm", "-l", "mse", "-P", "personalized", "--trials", "0"],
                        2, "--trials"),
    "tune --trials -1": (lambda p: ["tune", *C(p), "-a", "lstm", "-l", "mse", "-P", "personalized", "-n", "-1"],
                         2, "--trials"),
    "sweep --workers 0": (lambda p: ["sweep", *C(p), "--workers", "0"], 2, "--workers"),
    "unknown option": (lambda p: ["status", *C(p), "--colour"], 2, "No such option: --colour"),
    "unknown command": (lambda p: ["trian"], 2, "No such command 'trian'"),
    "unknown --only key": (lambda p: ["sweep", "plan", *C(p), "--only", "colour=red"], 2, "colour"),
    "unknown arch flag": (lambda p: ["train", *C(p), "-a", "transformer", "-l", "mse", "-P", "personalized"], 2,
                          "arch 'transformer': must be one of"),
    "ui --port 99999": (lambda p: ["ui", *C(p), "--port", "99999"], 2, "--port 99999: must be between 1 and 65535"),
    "ui on a busy port": (lambda p: ["ui", *C(p), "--port", str(p.silent_port)], 2, "cannot listen on 127.0.0.1:"),
    "report --table unknown": (lambda p: ["report", *C(p), "--table", "nosuch"], 2, "nosuch"),
    # -- files and folders ---------------------------------------------------------------
    "report --out is a file": (lambda p: ["report", *C(p), "--out", str(p.write("out.txt", "x"))], 2,
                               "out.txt: is a file, not a folder"),
    "report --out under a file": (lambda p: ["report", *C(p), "--out", str(p.write("out.txt", "x") / "r")], 2,
                                  "is a file, so no folder can be created there"),
    "data generate --out is a file": (lambda p: ["data", "generate", *C(p), "--out", str(p.write("f.bin", "x"))], 2,
                                      "f.bin: is a file"),
    "generation that fails early": (lambda p: ["data", "generate", *C(p), "--anatomy",
                                               str(p.write("bad.stl", "not a mesh")), "--out", str(p.root / "gen"),
                                               *TINY_GENERATE], 2, "bad.stl"),
    "missing anatomy file": (lambda p: ["data", "generate", *C(p), "--anatomy", str(p.root / "gone.vtu"), "--out",
                                        str(p.root / "gen"), *TINY_GENERATE], 2, "gone.vtu"),
    "garbage CSV row (stats)": (lambda p: ["data", "stats", str(edit_csv_row(p).parent)], 2,
                                "p00.csv line 4: frame must be a whole number, got 'zz'"),
    "garbage CSV row (preview)": (lambda p: ["data", "preview", str(edit_csv_row(p).parent), "--out",
                                             str(p.root / "prev.png")], 2,
                                  "p00.csv line 4: frame must be a whole number, got 'zz'"),
    "missing dataset": (lambda p: ["data", "stats", str(p.root / "nodata")], 2, "nodata: dataset directory not found"),
    "corrupt dataset.json": (lambda p: ["data", "stats", str(p.write("data/tiny/dataset.json", "{nope").parent)], 2,
                             "dataset.json: not valid JSON"),
    "missing frame file": (lambda p: ["data", "stats", str(_remove_frame(p))], 2, "not found"),
    "corrupt --latency-from": (lambda p: ["report", *C(p), "--latency-from", str(p.write("lat.json", "[{"))], 2,
                               "--latency-from"),
    "mistyped runs.uri (track)": (lambda p: ["track", str(p.root / "data" / "tiny" / "p00" / "ur"), *C(p), "--run",
                                             "0" * 32, "--set", "runs.uri=sqlite:///runs/mlfow.db"], 2,
                                  "runs.uri sqlite:///"),
    "mistyped storage.url (tune --show)": (lambda p: ["tune", *C(p), "--show", "--study", "s", "--storage",
                                                      "sqlite:///runs/swep.db"], 2, "holds no study yet"),
    # -- servers that are down or never answer ------------------------------------------------
    "hung tracking server (report)": (lambda p: ["report", *C(p), "--set", f"runs.uri={hung(p)}"], 2,
                                      "no answer within 1 s"),
    "hung tracking server (sweep)": (lambda p: ["sweep", *C(p), "--set", f"runs.uri={hung(p)}"], 2,
                                     "no answer within 1 s"),
    "hung tracking server (train)": (lambda p: ["train", *C(p), "-a", "baseline", "-l", "mse", "-P", "personalized",
                                                "--set", f"runs.uri={hung(p)}"], 2, "no answer within 1 s"),
    "hung PostgreSQL tracking": (lambda p: ["report", *C(p), "--set", f"runs.uri={hung(p, 'postgresql')}"], 2,
                                 "runs.uri postgresql://bob:***@127.0.0.1"),
    "refused PostgreSQL tracking": (lambda p: ["sweep", *C(p), "--set", "runs.uri=postgresql://bob:hunter2@"
                                               "127.0.0.1:1/db"], 2, "cannot connect within 2 s"),
    "hung sweep storage": (lambda p: ["status", *C(p), "--storage", hung(p, "postgresql")], 2,
                           "sweep storage postgresql+psycopg://bob:***@127.0.0.1"),
    "refused sweep storage": (lambda p: ["sweep", *C(p), "--storage", "postgresql://bob:hunter2@127.0.0.1:1/db"],
                              2, "check the host, port"),
    "hung tune storage": (lambda p: ["tune", *C(p), "--show", "--study", "s", "--storage", hung(p, "postgresql")],
                          2, "storage.url postgresql+psycopg://bob:***@127.0.0.1"),
    "refused tune storage": (lambda p: ["tune", *C(p), "-a", "lstm", "-l", "mse", "-P", "personalized", "-n", "1",
                                        "--storage", "postgresql://bob:hunter2@127.0.0.1:1/db"], 2, "Connection refused"),
    "missing tune database": (lambda p: ["tune", *C(p), "--show", "--study", "s", "--storage",
                                         "postgresql://postgres:hunter2@127.0.0.1:5432/no_such_db_here"], 2,
                              "storage.url postgresql+psycopg://postgres:***@127.0.0.1:5432/no_such_db_here"),
    "ui on a hung PostgreSQL store": (lambda p: ["ui", *C(p), "--port", str(free_port()), "--set",
                                                 f"runs.uri={hung(p, 'postgresql')}"], 2, "cannot connect"),
    "ui on a refused PostgreSQL store": (lambda p: ["ui", *C(p), "--set", "runs.uri=postgresql://bob:hunter2@"
                                                    "127.0.0.1:1/db"], 2, "runs.uri postgresql://bob:***@"),
    "ui for a remote server": (lambda p: ["ui", *C(p), "--set", f"runs.uri={hung(p)}"], 2, "already a server"),
    # issue 37.6: the UI has no authentication: another interface than loopback only when asked for
    "ui --host 0.0.0.0 without --expose": (lambda p: ["ui", *C(p), "--host", "0.0.0.0", "--port", str(free_port())],
                                           2, "--host 0.0.0.0: not a loopback address; MLflow's UI has no "
                                              "authentication"),
}


def _remove_frame(p: Project) -> Path:
    root = p.root / "data" / "tiny"
    next(root.rglob("*.png")).unlink()
    return root


@pytest.mark.parametrize("case", list(CATALOGUE))
def test_bad_input_is_one_line_naming_the_culprit(cli, project, case):
    make, expected_code, culprit = CATALOGUE[case]
    args = make(project)
    before = project.files()
    code, out, err = cli(*args)
    assert code == expected_code, f"exit {code}\nstdout: {out}\nstderr: {err}"
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one line on stderr, got:\n{err}"
    assert lines[0].startswith("error: ") and culprit in lines[0], lines[0]
    assert "Traceback" not in out + err
    assert "hunter2" not in out + err
    created = project.files() - before
    assert not created, f"left behind: {sorted(created)}"


@pytest.mark.heavy  # a CLI process rendering a dataset
def test_sigint_during_data_generate_exits_130_with_how_to_resume(tmp_path):
    """Ctrl-C in a terminal reaches the whole process group (the renderers too): one line, exit 130, resumable."""
    out = tmp_path / "gen"
    code = "import sys; from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()"
    args = ["data", "generate", "-c", str(REPO / "experiments.yaml"), "--anatomy", "procedural", "--out", str(out),
            *TINY_GENERATE, "--set", "dataset.generate.max_frames=400", "--trajectories", "60", "--workers", "2"]
    # A shell that starts jobs in the background hands them SIGINT ignored (as CI may run us): restore the
    # default, as in a terminal, so the interpreter turns Ctrl-C into KeyboardInterrupt.
    proc = subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, env={**os.environ, "COLUMNS": "200"},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    end = time.monotonic() + 120
    # ~4,000 frames: seconds of rendering left when the first frame appears, so the signal lands mid-way
    while not any(out.rglob("*.png")):  # wait until frames are being rendered
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < end, "no frame rendered"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stdout + stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("interrupted: ") and "run the same command again" in lines[0], stderr
    assert "Traceback" not in stdout + stderr
    assert any(out.rglob("*.png")) and not (out / "dataset.json").exists()  # kept for the re-run, not finished


def test_a_missing_dataset_root_says_a_new_dataset_will_be_generated_there(tmp_path):
    cfg = Config(name="t").with_values({
        "dataset.root": str(tmp_path / "dta" / "synthetic"), "dataset.generate.patients": 1,
        "dataset.generate.trajectories": 1, "dataset.generate.image_size": 16, "dataset.generate.max_frames": 2,
        "dataset.generate.voxel_mm": 1.0, "dataset.generate.lobes": ["br"], "dataset.generate.workers": 1})
    notes: list[str] = []
    ensure_dataset(cfg, progress=False, note=notes.append)
    assert len(notes) == 1 and str(tmp_path / "dta" / "synthetic") in notes[0] and "does not exist" in notes[0]
    ensure_dataset(cfg, progress=False, note=notes.append)  # now it exists: nothing to say
    assert len(notes) == 1


# -- properties -----------------------------------------------------------------------

SECTIONS = sorted(Config.model_fields)
scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                    st.text(max_size=12))
keys = st.one_of(st.sampled_from(SECTIONS + ["lr", "arch", "steps", "uri", "root", "seed"]), st.text(max_size=8))
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(keys, inner, max_size=3),
                      max_leaves=12)
PROPERTY = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@PROPERTY
@given(data=st.dictionaries(keys, values, max_size=6))
def test_any_yaml_mapping_loads_or_is_a_config_error(tmp_path, data):
    path = tmp_path / "fuzz.yaml"
    path.write_text(yaml.safe_dump(data, allow_unicode=True))
    try:
        load_config(path)
    except ConfigError as exc:
        assert str(exc).strip() and "Traceback" not in str(exc)


# Independent problems with the key path each must be reported under.
PROBLEMS = {
    "train.lr": ("train", "lr", -1),
    "train.steps": ("train", "steps", "many"),
    "grid.arch": ("grid", "arch", ["transformer"]),
    "data.window": ("data", "window", 0),
    "sweep.max_retries": ("sweep", "max_retries", -2),
    "runs.timeout_s": ("runs", "timeout_s", 0),
    "splits.colour": ("splits", "colour", 1),
    "model.dropout": ("model", "dropout", 1.5),
}


@PROPERTY
@given(chosen=st.lists(st.sampled_from(sorted(PROBLEMS)), min_size=1, unique=True))
def test_every_problem_of_a_config_is_reported_at_once(tmp_path, chosen):
    data: dict = {"name": "t"}
    for name in chosen:
        section, key, value = PROBLEMS[name]
        data.setdefault(section, {})[key] = value
    path = tmp_path / "many.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert all(name in message for name in chosen), (chosen, message)
    assert len(message.splitlines()) == (1 if len(chosen) == 1 else len(chosen) + 1)


dotted = st.from_regex(r"[A-Za-z_][A-Za-z0-9_-]{0,6}(\.[A-Za-z0-9_-]{1,6}){0,3}", fullmatch=True)


@PROPERTY
@given(text=st.text(max_size=40))
def test_parse_override_accepts_or_rejects_any_text_with_a_config_error(text):
    try:
        key, _ = parse_override(text)
    except ConfigError as exc:
        assert "--set" in str(exc)
    else:
        assert "=" in text and key == text.partition("=")[0].strip()


@PROPERTY
@given(key=dotted, value=st.one_of(st.integers(), st.booleans(), st.lists(st.integers(), max_size=4),
                                   st.floats(allow_nan=False, allow_infinity=False)))
def test_parse_override_round_trips_values(key, value):
    text = repr(value).lower() if isinstance(value, bool) else repr(value)
    got_key, got = parse_override(f"{key}={text}")
    assert got_key == key
    if isinstance(value, float):
        assert float(got) == value  # PyYAML reads '1e-05' as text; pydantic's float fields accept it
    else:
        assert got == value and type(got) is type(value)


@PROPERTY
@given(key=dotted, rest=st.text(alphabet="abcXYZ019=&_-", max_size=20))
def test_parse_override_keeps_everything_after_the_first_equals_sign(key, rest):
    url = f"postgresql://u:p@h/db?a={rest}"
    assert parse_override(f"{key}={url}") == (key, url)


@PROPERTY
@given(overrides=st.lists(st.text(max_size=30), max_size=3))
def test_random_set_overrides_never_escape_as_anything_but_a_config_error(project, overrides):
    try:
        load_config(project.config, overrides=overrides)
    except ConfigError:
        pass


@pytest.mark.parametrize("args", [["config"], ["config", "--grid"], ["sweep", "plan"]])
def test_no_printed_form_of_the_config_shows_a_password(cli, project, args, monkeypatch):
    monkeypatch.setenv("BP_SECRET", "hunter2")
    code, out, err = cli(*args, *C(project), "--set", "runs.uri=http://alice:${BP_SECRET}@127.0.0.1:9/mlflow",
                         "--set", "storage.url=sqlite:///runs/sweep.db",
                         "--set", "dataset.csv.frames=postgresql://bob:hunter2@db/x")
    assert "hunter2" not in out + err
    if args == ["config"]:
        assert code == 0 and "http://alice:***@127.0.0.1:9/mlflow" in out and "bob:***@db" in out


# == bad inputs by family (issue 22.7) =====================================================================
# Each family is a set of cases that must behave alike: exit 2, one line on stderr naming the culprit, no
# traceback, and nothing created beyond what the case allows (a dataset problem found while decoding frames
# may leave the frame-cache folder). New cases join a family; the test does not change.

RUN = ["-a", "baseline", "-l", "mse", "-P", "personalized"]


def readonly(p: Project) -> Path:
    """The project copied onto a tmpfs that is then remounted read-only (skips where mounting is not allowed)."""
    mount = p.root / "ro"
    mount.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(mount)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    p.mounts.append(mount)
    subprocess.run(["cp", "-a", str(p.config), str(p.root / "data"), str(mount)], check=True)
    subprocess.run(["mount", "-o", "remount,ro", str(mount)], check=True)
    return mount / p.config.name


def dataset_file(p: Project) -> list[str]:
    return ["-c", str(p.config), "--set", f"dataset.root={p.write('data/file.bin', 'not a folder')}"]


def truncate_frame(p: Project) -> Path:
    root = p.root / "data" / "tiny"
    frame = sorted(root.rglob("*.png"))[0]
    frame.write_bytes(frame.read_bytes()[:40])  # a PNG cut short, as by a full disk or an interrupted copy
    return root


def frame_folder(p: Project) -> Path:
    root = p.root / "data" / "tiny"
    frame = sorted(root.rglob("*.png"))[0]
    frame.unlink()
    frame.mkdir()
    return root


COMMANDS_THAT_WRITE: dict[str, list[str]] = {
    "train": ["train", *RUN], "sweep": ["sweep"], "sweep plan": ["sweep", "plan"],
    "tune": ["tune", *RUN, "-n", "1"],
}

# family -> case -> (argv maker, text the line must contain, paths the case may create)
FAMILIES: dict[str, dict[str, tuple[Callable[[Project], list[str]], str, tuple[str, ...]]]] = {
    "paths": {
        **{f"config on a read-only file system ({name})": (
            lambda p, argv=argv: [*argv, "-c", str(readonly(p))], "read-only file system", ())
           for name, argv in COMMANDS_THAT_WRITE.items()},
        **{f"dataset.root is a file ({name})": (lambda p, argv=argv: [*argv, *dataset_file(p)],
                                                "is a file, not a dataset folder", ())
           for name, argv in COMMANDS_THAT_WRITE.items()},
        "tracking database is a folder": (lambda p: ["train", *RUN, *C(p), "--set", "runs.uri=sqlite:///data"],
                                          "is a folder, not a database file", ()),
        "sweep storage is a folder": (lambda p: ["sweep", *C(p), "--set", "storage.url=sqlite:///data"],
                                      "storage.url", ()),
        "artifacts folder is a file": (lambda p: ["train", *RUN, *C(p), "--set",
                                                  f"runs.artifacts={p.config}"], "is a file, not a folder", ()),
        "checkpoints under a file": (lambda p: ["sweep", *C(p), "--set", f"runs.checkpoints={p.config}/ck"],
                                     "is a file, so no folder can be created there", ()),
        "cache folder under a file": (lambda p: ["tune", *RUN, *C(p), "--set", f"data.cache_dir={p.config}/c"],
                                      "data.cache_dir", ()),
        "dataset.json is a folder": (lambda p: ["data", "stats", str(_json_folder(p))], "dataset.json", ()),
        "a frame is a folder": (lambda p: ["data", "preview", str(frame_folder(p)), "--out",
                                           str(p.root / "prev.png")], "t000_f0000.png", ()),
        "--latency-from is a folder": (lambda p: ["report", *C(p), "--latency-from", str(p.root / "data")],
                                       "--latency-from", ()),
    },
    "YAML constructs": {
        "recursive alias in a list": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: t\nx: &a [1, *a]\n"))],
                                      "e.yaml:2: recursive YAML alias", ()),
        "recursive alias in a mapping": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: t\ntrain: &t\n"
                                                                                 "  lr: 1\n  sub: *t\n"))],
                                         "recursive YAML alias", ()),
        "alias bomb": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: t\n" + _laughs()))],
                       "YAML aliases expand to more than", ()),
        "flow mapping with a repeated key": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: t\n"
                                                                                     "train: {lr: 1, lr: 2}\n"))],
                                             "e.yaml:2: duplicate key 'lr'", ()),
        "repeated key in a --set value": (lambda p: ["config", *C(p), "--set", "train={lr: 1, lr: 2}"],
                                          "duplicate key 'lr'", ()),
        "python tag": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: !!python/object/apply:os.system "
                                                              "['touch pwned']\n"))], "e.yaml:1", ()),
        "local tag": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: !shell t\n"))], "e.yaml:1", ()),
        "binary tag": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: !!binary dGlueQ==\n"))],
                       "name", ()),
        "timestamp for a name": (lambda p: ["config", "-c", str(p.write("e.yaml", "name: 2024-01-01\n"))],
                                 "name", ()),
        "set tag for a list": (lambda p: ["config", *C(p), "--set", "grid.seed=!!set {1, 2}"], "grid.seed", ()),
    },
    "numbers": {
        "train.lr=.inf (train)": (lambda p: ["train", *RUN, *C(p), "--set", "train.lr=.inf"],
                                  "train.lr: Infinity: input should be a finite number", ()),
        "dataset.generate.step_mm with .nan": (lambda p: ["config", *C(p), "--set",
                                                          "dataset.generate.step_mm=[.nan, 2]"],
                                               "dataset.generate.step_mm", ()),
        "negative --seed (train)": (lambda p: ["train", *RUN, *C(p), "--seed", "-1"], "seed", ()),
        "--seed past 2**32-1 (tune)": (lambda p: ["tune", *RUN, *C(p), "--seed", "4294967296"], "seed", ()),
        "negative splits.seed (sweep)": (lambda p: ["sweep", *C(p), "--set", "splits.seed=-3"],
                                         "splits.seed: -3", ()),
        "boolean for a count": (lambda p: ["config", *C(p), "--set", "train.steps=true"],
                                "train.steps: true: input should be a valid integer", ()),
        "numeric string for a rate": (lambda p: ["config", *C(p), "--set", "train.lr='0.1'"],
                                      "train.lr: \"0.1\": input should be a valid number", ()),
        "fraction for a count": (lambda p: ["config", *C(p), "--set", "train.steps=2.5"], "train.steps", ()),
        # issue 37.4: every number has a range, named in the one line
        "train.steps=10^32 (config)": (lambda p: ["config", *C(p), "--set", f"train.steps={10**32}"],
                                       f"train.steps: {10**32}: input should be less than or equal to 10000000 "
                                       "(allowed range [1, 10000000])", ()),
        "train.batch_size=10^20 (train)": (lambda p: ["train", *RUN, *C(p), "--set", f"train.batch_size={10**20}"],
                                           "(allowed range [1, 65536])", ()),
        "dataset.generate.patients=10^12 (data generate)": (
            lambda p: ["data", "generate", *C(p), "--out", str(p.root / "gen"), *TINY_GENERATE, "--patients",
                       str(10**12)], "dataset.generate.patients: 1000000000000", ()),
        "dataset.generate.workers=10^8 (data generate)": (
            lambda p: ["data", "generate", *C(p), "--out", str(p.root / "gen"), *TINY_GENERATE, "--set",
                       f"dataset.generate.workers={10**8}"], "(allowed range [1, 1024])", ()),
        # issue 40.2: a choice that matches no spelling names the choices and the spellings
        "train.precision=64 (config)": (lambda p: ["config", *C(p), "--set", "train.precision=64"],
                                        "train.precision: 64: must be one of 'auto', '32', '16-mixed' or 'bf16-mixed' "
                                        "(also written: 32 as a number", ()),
    },
    "tune.space": {
        "unknown key (config)": (lambda p: ["config", *C(p), "--set", "tune.space={train.lrr: {type: float, "
                                            "low: 1, high: 2}}"], "tune.space.train.lrr", ()),
        "low > high (config)": (lambda p: ["config", *C(p), "--set", "tune.space={train.lr: {type: float, "
                                           "low: 0.1, high: 0.01}}"], "needs low < high", ()),
        "low > high (tune)": (lambda p: ["tune", *RUN, *C(p), "--set", "tune.space={train.lr: {type: float, "
                                         "low: 0.1, high: 0.01}}"], "needs low < high", ()),
        "log scale from 0": (lambda p: ["config", *C(p), "--set", "tune.space={train.lr: {type: float, low: 0, "
                                        "high: 0.1, log: true}}"], "log scale needs low > 0", ()),
        "a choice the setting refuses": (lambda p: ["config", *C(p), "--set", "tune.space={train.schedule: "
                                                    "{type: categorical, choices: [cosine, zigzag]}}"],
                                         "tune.space.train.schedule", ()),
        "a range past the setting's bound": (lambda p: ["sweep", "plan", *C(p), "--set", "tune.space="
                                                        "{model.dropout: {type: float, low: 0.1, high: 1.5}}"],
                                             "tune.space.model.dropout", ()),
        "not a run setting": (lambda p: ["config", *C(p), "--set", "tune.space={sweep.poll_s: {type: float, "
                                         "low: 1, high: 2}}"], "only run settings can be tuned", ()),
        "empty choices": (lambda p: ["config", *C(p), "--set", "tune.space={train.schedule: {type: categorical, "
                                     "choices: []}}"], "non-empty 'choices'", ()),
        # issue 37.4: a step has a range too (0, high - low]: 1e30 left one value to search, without a word
        "step beyond the range (config)": (lambda p: ["config", *C(p), "--set", "tune.space={train.lr: {type: "
                                                      "float, low: 0.0001, high: 0.001, step: 1e30}}"],
                                           "tune.space.train.lr: step 1e+30 outside its range (0, high - low] = "
                                           "(0, 0.0009]", ()),
        "step 0 (config)": (lambda p: ["config", *C(p), "--set", "tune.space={model.dropout: {type: float, "
                                       "low: 0, high: 0.5, step: 0}}"], "step 0 outside its range", ()),
    },
    "datasets": {
        "truncated PNG (data preview)": (lambda p: ["data", "preview", str(truncate_frame(p)), "--out",
                                                    str(p.root / "prev.png")], "cannot decode frame", ()),
        "truncated PNG (train)": (lambda p: [*_(truncate_frame(p)), "train", *RUN, *C(p)], "cannot decode frame",
                                  ("runs",)),  # the frame cache's folder and lock
        "text file named .png (data preview)": (lambda p: ["data", "preview", str(_text_frame(p)), "--out",
                                                           str(p.root / "prev.png")], "cannot decode frame", ()),
        # issue 37.4: a pose beyond its bound is corruption, not a camera (data stats printed an inf step)
        "pose x=1e308 (data stats)": (lambda p: ["data", "stats", str(_pose(p, "pos_x", "1e308"))],
                                      "p00.csv line 2: out-of-range pose value x=1e+308 (allowed: finite, positions "
                                      "within ±1,000,000 voxels)", ()),
        "angle beyond 720° (train)": (lambda p: [*_(_pose(p, "Rz", "5000")), "train", *RUN, *C(p)],
                                      "p00.csv line 2: out-of-range pose value rz=5000", ("runs",)),
    },
    # issue 32.5: a symlink loop is one line wherever a path is read (pathcheck.resolve; the CLI's last resort)
    "symlink loops": {
        "dataset folder (data stats)": (lambda p: ["data", "stats", str(loop(p))], "symbolic link loop", ()),
        "dataset folder (data preview)": (lambda p: ["data", "preview", str(loop(p)), "--out",
                                                     str(p.root / "prev.png")], "symbolic link loop", ()),
        "dataset.root (sweep)": (lambda p: ["sweep", *C(p), *_(loop(p)), "--set", "dataset.root=loop/tiny"],
                                 "dataset.root loop/tiny: a symbolic link loop", ()),
        "runs.artifacts (train)": (lambda p: ["train", *RUN, *C(p), *_(loop(p)), "--set", "runs.artifacts=loop/a"],
                                   "runs.artifacts loop/a: a symbolic link loop", ()),
        "runs.checkpoints absolute (config)": (lambda p: ["config", *C(p), "--set",
                                                          f"runs.checkpoints={loop(p)}/ck"],
                                               "runs.checkpoints", ()),
        "a sqlite:/// path (status)": (lambda p: ["status", *C(p), *_(loop(p)), "--set",
                                                  "storage.url=sqlite:///loop/sweep.db"],
                                       "storage.url", ()),
        "an absolute sqlite:/// path (report)": (lambda p: ["report", *C(p), "--set",
                                                            f"runs.uri=sqlite:///{loop(p)}/m.db"], "runs.uri", ()),
        "data generate --out": (lambda p: ["data", "generate", *C(p), "--out", str(loop(p) / "gen"),
                                           *TINY_GENERATE], "--out", ()),
        "the config file": (lambda p: ["config", "-c", str(loop(p))], "symbolic link loop", ()),
        # issue 37.5: a loop at a dataset's own files is a loop, not "not found"
        "dataset.json (data stats)": (lambda p: ["data", "stats", str(_looped(p, "dataset.json"))],
                                      "dataset.json: a symbolic link loop", ()),
        "p00.csv (data stats)": (lambda p: ["data", "stats", str(_looped(p, "p00.csv"))],
                                 "p00.csv: a symbolic link loop", ()),
    },
    # issue 32.5: a dataset reads only its own files; outputs never go to system folders
    "paths leaving their root": {
        "patient ../escaped (data stats)": (lambda p: ["data", "stats", str(_patient(p, "../escaped"))],
                                            "patients[0] '../escaped'", ()),
        "patient /abs (train)": (lambda p: ["train", *RUN, *C(p), *_(_patient(p, str(p.root / "escaped")))],
                                 "a patient name is a file name", ("runs",)),
        "frame filename ../ (data stats)": (lambda p: ["data", "stats", str(_frame_name(p, "../../outside.png"))],
                                            "p00.csv line 2: frame file '../../outside.png' is outside", ()),
        "absolute frame filename (train)": (lambda p: [*_(_frame_name(p, str(p.root / "outside.png"))), "train",
                                                       *RUN, *C(p)], "p00.csv line 2", ("runs",)),
        "runs.artifacts=/etc": (lambda p: ["config", *C(p), "--set", "runs.artifacts=/etc"],
                                "runs.artifacts /etc: a system folder", ()),
        "runs.checkpoints=/ (sweep)": (lambda p: ["sweep", *C(p), "--set", "runs.checkpoints=/"],
                                       "runs.checkpoints /: a system folder", ()),
        "runs.artifacts under /usr (train)": (lambda p: ["train", *RUN, *C(p), "--set", "runs.artifacts=/usr/lib/x"],
                                              "a system folder", ()),
        # issue 37.5: the same rules for every path every command writes or reads
        "lobe ../.. in dataset.json (data stats)": (lambda p: ["data", "stats", str(_lobe(p, "../.."))],
                                                    "dataset.json: lobes[1] '../..': a lobe name is a folder name", ()),
        "data generate --out /etc/bp": (lambda p: ["data", "generate", *C(p), "--out", "/etc/bp", *TINY_GENERATE],
                                        "--out /etc/bp: a system folder", ()),
        "report --out /usr/share/bp": (lambda p: ["report", *C(p), "--out", "/usr/share/bp"],
                                       "--out /usr/share/bp: a system folder", ()),
        "data preview --out /etc/x.png": (lambda p: ["data", "preview", str(p.root / "data" / "tiny"), "--out",
                                                     "/etc/x.png"], "--out /etc/x.png: a system folder", ()),
        "runs.uri in /etc (config)": (lambda p: ["config", *C(p), "--set", "runs.uri=sqlite:////etc/bp/m.db"],
                                      "runs.uri /etc/bp/m.db: a system folder", ()),
    },
    # issue 32.6: a damaged SQLite store names the file and what to do
    "damaged stores": {
        "truncated mlflow.db (report)": (lambda p: ["report", *C(p), *_(_damaged(p, "runs/mlflow.db"))],
                                         "runs/mlflow.db: damaged SQLite database (database disk image is "
                                         "malformed", ()),
        "truncated mlflow.db (sweep)": (lambda p: ["sweep", *C(p), *_(_damaged(p, "runs/mlflow.db"))],
                                        "move it aside", ()),
        "truncated mlflow.db (status)": (lambda p: ["status", *C(p), *_(_damaged(p, "runs/mlflow.db"),
                                                                         _damaged(p, "runs/sweep.db"))],
                                         "damaged SQLite database", ()),
        "truncated sweep.db (status)": (lambda p: ["status", *C(p), *_(_damaged(p, "runs/sweep.db"))],
                                        "storage.url " , ()),
        "sweep.db not a database (sweep)": (lambda p: ["sweep", *C(p), *_(p.write("runs/sweep.db", b"x" * 4096))],
                                            "(file is not a database)", ()),
        "sweep.db not a database (tune)": (lambda p: ["tune", *RUN, *C(p), "-n", "1",
                                                      *_(p.write("runs/sweep.db", b"x" * 4096))],
                                           "sweep.db: damaged SQLite database", ("runs",)),
    },
    # issue 32.7: an undefined ${VAR} is an error naming the key and the variable (no folder named ${VAR})
    "environment": {
        "undefined ${VAR} in a path (sweep)": (lambda p: ["sweep", *C(p), "--set",
                                                          "runs.checkpoints=${BP_UNDEFINED_32}/ck"],
                                               "runs.checkpoints: environment variable ${BP_UNDEFINED_32} is not "
                                               "set", ()),
        "undefined ${VAR} in a URL (config)": (lambda p: ["config", *C(p), "--set",
                                                          "storage.url=postgresql://u:${BP_UNDEFINED_32}@h/db"],
                                               "storage.url: environment variable ${BP_UNDEFINED_32}", ()),
        "undefined ${VAR} in the file (train)": (lambda p: ["train", *RUN, "-c", str(p.write(
            "e2.yaml", p.config.read_text() + "data: {cache_dir: '${BP_UNDEFINED_32}/cache'}\n"))],
            "data.cache_dir: environment variable ${BP_UNDEFINED_32}", ()),
    },
}


def _(*_made) -> list[str]:
    """Build a case's input for its side effect (the argv follows)."""
    return []


def _laughs() -> str:
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 7)]
    return "\n".join(lines) + "\n"


def loop(p: Project) -> Path:
    """``<project>/loop``: a symbolic link to itself."""
    link = p.root / "loop"
    if not link.is_symlink():
        link.symlink_to(link)
    return link


def _looped(p: Project, name: str) -> Path:
    """The tiny dataset with its ``name`` replaced by a symbolic link to itself."""
    root = p.root / "data" / "tiny"
    (root / name).unlink()
    (root / name).symlink_to(root / name)
    return root


def _pose(p: Project, column: str, value: str) -> Path:
    """The tiny dataset whose first CSV row has ``value`` in ``column``."""
    root = p.root / "data" / "tiny"
    csv = root / "p00.csv"
    lines = csv.read_text().splitlines()
    header, row = lines[0].split(","), lines[1].split(",")
    row[header.index(column)] = value
    lines[1] = ",".join(row)
    csv.write_text("\n".join(lines) + "\n")
    return root


def _lobe(p: Project, name: str) -> Path:
    root = p.root / "data" / "tiny"
    meta = __import__("json").loads((root / "dataset.json").read_text())
    meta["lobes"] = [*meta.get("lobes", ["ur"]), name]
    (root / "dataset.json").write_text(__import__("json").dumps(meta))
    return root


def _patient(p: Project, name: str) -> Path:
    """The tiny dataset with ``name`` as its first patient, and a valid CSV where that name leads."""
    root = p.root / "data" / "tiny"
    meta = __import__("json").loads((root / "dataset.json").read_text())
    target = (root / f"{name}.csv") if not Path(name).is_absolute() else Path(f"{name}.csv")
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text((root / f"{meta['patients'][0]}.csv").read_text())
    meta["patients"][0] = name
    (root / "dataset.json").write_text(__import__("json").dumps(meta))
    return root


def _frame_name(p: Project, name: str) -> Path:
    """The tiny dataset whose first CSV row names the frame ``name`` (a file that exists there)."""
    root = p.root / "data" / "tiny"
    csv = root / "p00.csv"
    lines = csv.read_text().splitlines()
    header = lines[0].split(",")
    row = lines[1].split(",")
    frame = root / row[header.index("filename")]
    (root / name).parent.mkdir(parents=True, exist_ok=True)
    (root / name).write_bytes(frame.read_bytes())
    row[header.index("filename")] = name
    lines[1] = ",".join(row)
    csv.write_text("\n".join(lines) + "\n")
    return root


def _damaged(p: Project, name: str) -> Path:
    """A real SQLite database at ``name`` (in the project), cut to half its length as by a full disk."""
    path = p.root / name
    path.parent.mkdir(parents=True, exist_ok=True)
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE t (x BLOB)")
        db.executemany("INSERT INTO t VALUES (?)", [(os.urandom(2000),) for _ in range(40)])
    db.close()
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path


def _json_folder(p: Project) -> Path:
    root = p.root / "data" / "tiny"
    (root / "dataset.json").unlink()
    (root / "dataset.json").mkdir()
    return root


def _text_frame(p: Project) -> Path:
    root = p.root / "data" / "tiny"
    sorted(root.rglob("*.png"))[0].write_text("not an image\n")
    return root


@pytest.mark.parametrize("family,case", [(f, c) for f, cases in FAMILIES.items() for c in cases],
                         ids=[f"{f}: {c}" for f, cases in FAMILIES.items() for c in cases])
def test_each_family_of_bad_input_is_one_line_and_exit_2(cli, project, family, case):
    make, culprit, allowed = FAMILIES[family][case]
    args = make(project)
    before = project.files()
    code, out, err = cli(*args)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2, f"exit {code}\nstdout: {out}\nstderr: {err}"
    assert len(lines) == 1, f"expected one line on stderr, got:\n{err}"
    assert lines[0].startswith("error: ") and culprit in lines[0], lines[0]
    assert "Traceback" not in out + err and "all is well" not in out
    created = {f for f in project.files() - before if not any(f == a or f.startswith(a + "/") for a in allowed)}
    assert not created, f"left behind: {sorted(created)}"
    assert not (project.root / "pwned").exists()


# -- numbers, over the whole schema ---------------------------------------------------------------------------


def _settings(model=Config, prefix: str = "") -> list[tuple[str, set]]:
    """(dotted path, scalar types it takes) of every scalar setting of the config schema."""
    from typing import Annotated, Literal, Union, get_args, get_origin

    from pydantic import BaseModel

    out = []
    for name, field in model.model_fields.items():
        ann, path = field.annotation, f"{prefix}{name}"
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out += _settings(ann, f"{path}.")
            continue
        args = get_args(ann) if get_origin(ann) in (Union, getattr(__import__("types"), "UnionType")) else (ann,)
        args = tuple(get_args(a)[0] if get_origin(a) is Annotated else a for a in args)
        kinds = {a for a in args if a in (int, float, bool)}
        if kinds and not any(get_origin(a) is Literal for a in args):
            out.append((path, kinds))
    return out


SETTINGS = _settings()
FLOATS = [path for path, kinds in SETTINGS if float in kinds]
INTS = [path for path, kinds in SETTINGS if kinds == {int}]
SEEDS = [path for path in INTS if path.endswith("seed")] + ["grid.seed"]


def test_the_schema_walk_finds_the_settings_it_must():
    assert {"train.lr", "model.dropout", "runs.timeout_s", "sweep.heartbeat_s"} <= set(FLOATS)
    assert {"train.steps", "splits.seed", "dataset.generate.seed", "tune.seed"} <= set(INTS)


def _refused(overrides: list[str], path: str) -> str:
    with pytest.raises(ConfigError) as info:
        load_config(REPO / "experiments.yaml", overrides=overrides)
    message = str(info.value)
    assert path in message and len(message.splitlines()) == 1, message
    return message


@pytest.mark.parametrize("path", FLOATS)
@pytest.mark.parametrize("value", [".inf", "-.inf", ".nan"])
def test_every_float_setting_refuses_non_finite_values(path, value):
    assert "finite number" in _refused([f"{path}={value}"], path)


@pytest.mark.parametrize("path", FLOATS + INTS)
@pytest.mark.parametrize("value", ["true", "false", "'3'", "'1e-3'"])
def test_no_number_setting_coerces_booleans_or_text(path, value):
    _refused([f"{path}={value}"], path)


@PROPERTY
@given(path=st.sampled_from(SEEDS), seed=st.one_of(st.integers(max_value=-1), st.integers(min_value=2**32)))
def test_seeds_outside_0_to_2_32_are_refused_where_they_are_set(path, seed):
    value = f"[{seed}]" if path == "grid.seed" else str(seed)
    _refused([f"{path}={value}"], path)


@PROPERTY
@given(path=st.sampled_from(SEEDS), seed=st.integers(0, 2**32 - 1))
def test_every_seed_in_range_is_accepted(path, seed):
    load_config(REPO / "experiments.yaml", overrides=[f"{path}={f'[{seed}]' if path == 'grid.seed' else seed}"])


@PROPERTY
@given(lr=st.floats(min_value=1e-9, max_value=10, allow_nan=False))
def test_floats_written_with_an_exponent_are_numbers(lr):
    assert load_config(REPO / "experiments.yaml", overrides=[f"train.lr={lr:e}"]).train.lr == pytest.approx(lr)


# == issue 32: out of memory, damage found mid-command, secrets in every printed and recorded form =====



def _runs(p: Project) -> list:
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{p.root / 'runs' / 'mlflow.db'}")
    return client.search_runs([e.experiment_id for e in client.search_experiments()])


@pytest.mark.parametrize("failure", [MemoryError(), RuntimeError(
    "[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried to "
    "allocate 4000000000 bytes. Error code 12 (Cannot allocate memory)"),
    ImportError("/venv/lib/python3.11/site-packages/torch/lib/libtorch_cpu.so: failed to map segment from shared "
                "object")], ids=["MemoryError", "torch allocator", "library loaded under ulimit -v"])
@pytest.mark.heavy  # a real run
def test_out_of_memory_in_a_run_is_one_line_and_the_run_failed_with_it(cli, project, monkeypatch, failure):
    def allocate(*args, **kwargs):
        raise failure

    monkeypatch.setattr("bronchocli.training.run.fit_and_evaluate", allocate)
    code, out, err = cli("train", *RUN, *C(project))
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: out of memory"), err
    assert "ulimit -v" in lines[0] and "Traceback" not in out + err
    (run,) = _runs(project)
    assert run.info.status == "FAILED" and run.data.tags["failure_reason"].startswith("OutOfMemory: out of memory")


def test_real_allocation_failures_are_recognised_as_out_of_memory():
    import torch

    for allocate in (lambda: np.empty(2**50, dtype=np.uint8), lambda: torch.empty(2**50, dtype=torch.uint8)):
        with pytest.raises((MemoryError, RuntimeError)) as info:  # 1 PiB: no machine has it
            allocate()
        assert isinstance(out_of_memory(info.value), OutOfMemory), info.value
    assert out_of_memory(RuntimeError("shape mismatch")) is None and out_of_memory(ValueError("x")) is None


def test_damage_met_mid_command_is_one_line_naming_the_store(tmp_path):
    """A page damaged inside a SQLite file whose header is sound: the query fails later; the message names the
    stores this process opened and what to do (the CLI's last resort for it)."""
    path = tmp_path / "sweep.db"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE t (x BLOB)")
        db.executemany("INSERT INTO t VALUES (?)", [(os.urandom(3000),) for _ in range(60)])
    db.close()
    urls.check_sqlite(path, "storage.url")  # sound so far
    data = bytearray(path.read_bytes())
    data[4096:8192] = b"\xff" * 4096  # the table's root page
    path.write_bytes(bytes(data))
    urls.check_sqlite(path, "storage.url")  # the header still looks sound
    with pytest.raises(sqlite3.DatabaseError) as info:
        with sqlite3.connect(path) as db:
            db.execute("SELECT count(*), sum(length(x)) FROM t").fetchall()
    message = urls.damaged_message(info.value)
    assert message is not None and str(path) in message and "move it aside" in message, message
    assert urls.damaged_message(ValueError("something else")) is None


def test_out_of_memory_outside_a_run_is_one_line(cli, monkeypatch):
    def allocate(*args, **kwargs):
        raise ImportError("libopenblas.so.0: cannot allocate memory for thread-local data")

    monkeypatch.setattr("bronchocli.api.work.load_config", allocate)
    code, out, err = cli("config", "-c", str(REPO / "experiments.yaml"))
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: out of memory"), err


def _planted_storage(request) -> str:
    """A fresh schema of the local PostgreSQL (trust auth: the planted passwords are sent and ignored)."""
    psycopg = pytest.importorskip("psycopg")
    try:
        admin = psycopg.connect(host="127.0.0.1", port=5432, user="postgres", dbname="test", connect_timeout=3,
                                autocommit=True)
    except psycopg.Error as exc:
        pytest.skip(f"PostgreSQL at 127.0.0.1:5432/test unreachable: {exc}")
    schema = f"secrets_{os.getpid()}_{time.monotonic_ns()}"
    admin.execute(f"CREATE SCHEMA {schema}")

    def drop() -> None:
        admin.execute(f"DROP SCHEMA {schema} CASCADE")
        admin.close()

    request.addfinalizer(drop)
    return (f"postgresql://postgres:{SECRETS['userinfo']}@127.0.0.1:5432/test?options=-csearch_path%3D{schema}"
            f"&password={SECRETS['query']}")


SECRETS = {"userinfo": "Pl4nt-userinfo-32", "query": "Pl4nt-query-32", "env": "Pl4nt-env-32",
           "pgpass": "Pl4nt-pgpass-32"}


@pytest.mark.postgres  # _planted_storage: a schema of the local server
def test_a_planted_password_in_every_form_reaches_no_output_log_or_mlflow_record(cli, project, monkeypatch,
                                                                                   request):
    """issue 32.4: userinfo, ?password=, PGPASSWORD and .pgpass passwords are in the config of a real tiny
    sweep; none of them is in its output, any file it wrote (logs, the MLflow store: params, tags, artifacts)."""
    pgpass = project.write("pgpass", f"db.example:5432:*:bp:{SECRETS['pgpass']}\n")
    pgpass.chmod(0o600)
    monkeypatch.setenv("PGPASSFILE", str(pgpass))
    monkeypatch.setenv("PGPASSWORD", SECRETS["env"])
    secret_url = (f"postgresql://bp:{SECRETS['userinfo']}@db.example:5432/x?sslmode=require"
                  f"&password={SECRETS['query']}&note={SECRETS['env']}{SECRETS['pgpass']}")
    storage = _planted_storage(request)  # the claims table on PostgreSQL, both passwords in its URL
    args = [*C(project), "--set", f"dataset.csv.frames={secret_url}", "--set", "sweep.logs=runs/sweep-logs",
            "--set", f"storage.url={storage}"]
    outputs = []
    for argv in (["config"], ["sweep"], ["status"], ["report", "--out", "reports"]):
        code, out, err = cli(*argv, *args)
        outputs.append(out + err)
        assert code == 0, (argv, out, err)
    runs = _runs(project)  # the cell's run (and the sweep's parent run)
    assert runs and all(r.info.status == "FINISHED" for r in runs)
    assert all(not [f for f, v in SECRETS.items() if v in str(r.data.params) + str(r.data.tags)] for r in runs)
    assert "***" in outputs[0]  # the config shows where the password was
    assert "postgres:***@127.0.0.1" in outputs[1]  # the sweep prints its storage, redacted
    for text in outputs:
        assert not [form for form, s in SECRETS.items() if s in text], text
    written = [f for f in project.root.rglob("*") if f.is_file() and f != pgpass]
    assert any(f.name == "mlflow.db" for f in written) and any("sweep-logs" in str(f) for f in written)
    for f in written:
        data = f.read_bytes()
        leaked = [form for form, s in SECRETS.items() if s.encode() in data]
        assert not leaked, (f, leaked)
# -- roots that hold each other or a system folder (issue 32, item 1) -------------------------------------------

ROOTS: dict[str, tuple[list[str], str]] = {
    "checkpoints holding the artifacts (gc)": (["sweep", "gc", "--set", "runs.checkpoints=runs"],
                                               "runs.checkpoints {root}/runs: contains runs.artifacts"),
    "checkpoints holding the artifacts (train)": (["train", *RUN, "--set", "runs.checkpoints=runs"],
                                                  "runs.checkpoints {root}/runs: contains runs.artifacts"),
    # issue 37.5: `config` validates what `sweep` validates
    "checkpoints holding the artifacts (config)": (["config", "--set", "runs.checkpoints=runs"],
                                                   "runs.checkpoints {root}/runs: contains runs.artifacts"),
    "checkpoints holding the artifacts (sweep)": (["sweep", "--set", "runs.checkpoints=runs"],
                                                  "runs.checkpoints {root}/runs: contains runs.artifacts"),
    "cache is the checkpoints folder (sweep)": (["sweep", "--set", "data.cache_dir=runs/checkpoints"],
                                                "data.cache_dir {root}/runs/checkpoints: is the same folder as runs.checkpoints"),
    "logs inside the cache (sweep plan)": (["sweep", "plan", "--set", "sweep.logs=runs/cache/logs"],
                                                "data.cache_dir {root}/runs/cache: contains sweep.logs"),
    "artifacts in /etc (tune)": (["tune", *RUN, "--set", "runs.artifacts=/etc/bronchopose"],
                                 "runs.artifacts /etc/bronchopose: a system folder"),
    "checkpoints at / (gc)": (["sweep", "gc", "--set", "runs.checkpoints=/"], "runs.checkpoints /: a system folder"),
    "checkpoints at home (gc)": (["sweep", "gc", "--set", "runs.checkpoints='~'"], "a system folder"),
}


@pytest.mark.parametrize("case", list(ROOTS))
def test_roots_inside_each_other_or_system_folders_are_refused_in_one_line(cli, project, case):
    args, culprit = ROOTS[case]
    before = project.files()
    code, out, err = cli(*args, *C(project))
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, f"exit {code}\nstdout: {out}\nstderr: {err}"
    assert culprit.format(root=project.root) in lines[0], lines[0]
    assert project.files() == before
