"""A catalogue of bad inputs: every one gives its exit code and one line naming the culprit, no traceback,
nothing half-written; and property tests of the config loader and of `--set` parsing.

Each catalogue entry builds its bad input in a fresh project (a tiny dataset and a valid experiments.yaml on
SQLite stores) and runs the command in-process through the console script's own error path (`cli`).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from tinydata import write_tiny_dataset

from bronchocli.config import Config, load_config, parse_override
from bronchocli.errors import ConfigError
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
def project(tmp_path, silent_port) -> Project:
    write_tiny_dataset(tmp_path / "data" / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=3, image_size=16)
    config = tmp_path / "experiments.yaml"
    config.write_text(yaml.safe_dump({
        "name": "bad", "dataset": {"root": "data/tiny"},
        "grid": {"arch": ["baseline"], "rot_loss": ["mse"], "population": ["personalized"], "seed": [0]},
        "tracking": {"timeout_s": 1}, "train": {"steps": 2, "batch_size": 2, "threads": 1},
    }))
    return Project(tmp_path, config, silent_port)


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
    "negative timeout": (lambda p: ["config", *C(p), "--set", "tracking.timeout_s=-1"], 2, "tracking.timeout_s"),
    "unknown profile": (lambda p: ["config", *C(p), "--profile", "nosuch"], 2, "no such profile"),
    "--set without =": (lambda p: ["config", *C(p), "--set", "trainlr"], 2, "expected key.path=value"),
    "--set of an unknown section": (lambda p: ["config", *C(p), "--set", "foo.bar.baz=1"], 2,
                                    "--set foo.bar.baz=1: foo: unknown key 'foo'"),
    "--set into a value": (lambda p: ["config", *C(p), "--set", "name.x=1"], 2, "'name' in 'name.x' is a value"),
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
    "unknown --only key": (lambda p: ["sweep", *C(p), "--dry-run", "--only", "colour=red"], 2, "colour"),
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
    # -- servers that are down or never answer ------------------------------------------------
    "hung tracking server (report)": (lambda p: ["report", *C(p), "--set", f"tracking.uri={hung(p)}"], 2,
                                      "no answer within 1 s"),
    "hung tracking server (sweep)": (lambda p: ["sweep", *C(p), "--set", f"tracking.uri={hung(p)}"], 2,
                                     "no answer within 1 s"),
    "hung tracking server (train)": (lambda p: ["train", *C(p), "-a", "baseline", "-l", "mse", "-P", "personalized",
                                                "--set", f"tracking.uri={hung(p)}"], 2, "no answer within 1 s"),
    "hung PostgreSQL tracking": (lambda p: ["report", *C(p), "--set", f"tracking.uri={hung(p, 'postgresql')}"], 2,
                                 "tracking.uri postgresql://bob:***@127.0.0.1"),
    "refused PostgreSQL tracking": (lambda p: ["sweep", *C(p), "--set", "tracking.uri=postgresql://bob:hunter2@"
                                               "127.0.0.1:1/db"], 2, "cannot connect within 2 s"),
    "hung sweep storage": (lambda p: ["status", *C(p), "--storage", hung(p, "postgresql")], 2,
                           "sweep storage postgresql+psycopg://bob:***@127.0.0.1"),
    "refused sweep storage": (lambda p: ["sweep", *C(p), "--storage", "postgresql://bob:hunter2@127.0.0.1:1/db"],
                              2, "check the host, port"),
    "hung tune storage": (lambda p: ["tune", *C(p), "--show", "--study", "s", "--storage", hung(p, "postgresql")],
                          2, "storage.url postgresql+psycopg://bob:***@127.0.0.1"),
    "refused tune storage": (lambda p: ["tune", *C(p), "-a", "lstm", "-l", "mse", "-P", "personalized", "-n", "1",
                                        "--storage", "postgresql://bob:hunter2@127.0.0.1:1/db"], 2, "cannot connect"),
    "missing tune database": (lambda p: ["tune", *C(p), "--show", "--study", "s", "--storage",
                                         "postgresql://postgres:hunter2@127.0.0.1:5432/no_such_db_here"], 2,
                              "storage.url postgresql+psycopg://postgres:***@127.0.0.1:5432/no_such_db_here"),
    "ui on a hung PostgreSQL store": (lambda p: ["ui", *C(p), "--port", str(free_port()), "--set",
                                                 f"tracking.uri={hung(p, 'postgresql')}"], 2, "cannot connect"),
    "ui on a refused PostgreSQL store": (lambda p: ["ui", *C(p), "--set", "tracking.uri=postgresql://bob:hunter2@"
                                                    "127.0.0.1:1/db"], 2, "tracking.uri postgresql://bob:***@"),
    "ui for a remote server": (lambda p: ["ui", *C(p), "--set", f"tracking.uri={hung(p)}"], 2, "already a server"),
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
    "tracking.timeout_s": ("tracking", "timeout_s", 0),
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


@pytest.mark.parametrize("args", [["config"], ["config", "--grid"], ["sweep", "--dry-run"]])
def test_no_printed_form_of_the_config_shows_a_password(cli, project, args, monkeypatch):
    monkeypatch.setenv("BP_SECRET", "hunter2")
    code, out, err = cli(*args, *C(project), "--set", "tracking.uri=http://alice:${BP_SECRET}@127.0.0.1:9/mlflow",
                         "--set", "storage.url=sqlite:///runs/sweep.db",
                         "--set", "dataset.csv.frames=postgresql://bob:hunter2@db/x")
    assert "hunter2" not in out + err
    if args == ["config"]:
        assert code == 0 and "http://alice:***@127.0.0.1:9/mlflow" in out and "bob:***@db" in out
