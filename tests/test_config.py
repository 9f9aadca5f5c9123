"""Typed config: shipped files load and expand; malformed ones give one clear error each."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from bronchocli import config as C
from bronchocli.config.loading import _read_yaml as read_yaml
from bronchocli.errors import ConfigError


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "experiments.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def shipped_configs(repo: Path) -> list[tuple[Path, str | None]]:
    out = []
    for path in sorted(repo.glob("*.yaml")) + sorted((repo / "configs").glob("*.yaml")):
        raw = read_yaml(path)[0]
        out += [(path, None)] + [(path, p) for p in raw.get("profiles", {})]
    return out


def test_every_shipped_config_and_profile_loads_and_expands(repo):
    configs = shipped_configs(repo)
    assert (repo / "experiments.yaml", "paper") in configs
    for path, profile in configs:
        cfg = C.load_config(path, profile)
        cells = C.expand_grid(cfg, patients=[f"p{i:02d}" for i in range(cfg.dataset.generate.patients)])
        assert cells, (path, profile)
        assert len({c.key for c in cells}) == len(cells)


def test_defaults_and_relative_paths_resolve_against_the_config_dir(tmp_path):
    cfg = C.load_config(write(tmp_path, "name: t\n"))
    assert cfg.paths.base == tmp_path
    assert cfg.paths.mlflow_uri == f"sqlite:///{tmp_path}/runs/mlflow.db"
    assert cfg.paths.storage_url.startswith(f"sqlite:///{tmp_path}/runs/")
    assert cfg.paths.dataset == tmp_path / "data" / "synthetic"
    assert cfg.paths.cache == tmp_path / "runs" / "cache"
    assert cfg.paths.checkpoints == tmp_path / "runs" / "checkpoints"
    assert cfg.paths.artifacts == tmp_path / "runs" / "artifacts"
    assert cfg.paths.sweep_logs == tmp_path / "runs" / "sweep-logs"
    assert cfg.paths.anatomy is None and cfg.paths.centreline is None and cfg.paths.pretrained is None
    assert cfg.experiment_name == "t"
    server = C.Config(name="x", runs={"uri": "postgresql://u@h/db"})
    assert server.paths.mlflow_uri == "postgresql://u@h/db"


def test_paths_are_resolved_once_at_load_not_against_the_working_directory(tmp_path, monkeypatch):
    (tmp_path / "cfg").mkdir()
    cfg = C.load_config(write(tmp_path / "cfg", "name: t\ndataset: {root: ../ds, generate: {anatomy: a.vtu}}\n"))
    monkeypatch.chdir(tmp_path)
    assert cfg.paths.dataset == tmp_path / "ds"
    assert cfg.paths.anatomy == tmp_path / "cfg" / "a.vtu"
    assert cfg.with_values({"train.lr": 5e-4}).paths.dataset == tmp_path / "ds"  # a copy keeps the config's folder


def test_env_vars_expand_in_urls(tmp_path, monkeypatch):
    monkeypatch.setenv("PGPASS", "s3cret")
    cfg = C.load_config(write(tmp_path, "name: t\nstorage: {url: 'postgresql://u:${PGPASS}@h/db'}\n"))
    assert cfg.paths.storage_url == "postgresql://u:s3cret@h/db"
    assert "s3cret" not in cfg.to_yaml()
    with_password = C.load_config(write(tmp_path, "name: t\nstorage: {url: 'postgresql://u:s3cret@h/db'}\n"))
    assert "s3cret" not in with_password.to_yaml() and "postgresql://u:***@h/db" in with_password.to_yaml()


def test_profile_and_set_overrides_apply_in_order(repo):
    cfg = C.load_config(repo / "experiments.yaml", "paper", ["train.lr=3e-4", "grid.seed=4"])
    assert cfg.dataset.generate.image_size == 256  # from the profile
    assert cfg.train.lr == 3e-4 and cfg.grid.seed == [4]  # --set wins, scalars become lists
    # (grid.arch would be refused here: every stage of the paper profile decides arch itself)
    assert cfg.profile == "paper"


def test_every_problem_is_reported_at_once_with_line_value_and_allowed(tmp_path):
    path = write(tmp_path, """\
        name: t
        grid:
          arch: [baseline, resnet]
          colour: red
        train:
          lr: fast
          batch_size: 0
        """)
    with pytest.raises(ConfigError) as exc:
        C.load_config(path)
    msg = str(exc.value)
    assert "4 problems" in msg
    assert f"{path}:3: grid.arch[1]: \"resnet\": must be one of 'baseline', 'lstm'" in msg
    assert f"{path}:4: grid.colour: unknown key 'colour' (allowed: arch, folds" in msg
    assert f"{path}:6: train.lr: \"fast\"" in msg
    assert f"{path}:7: train.batch_size: 0: input should be greater than or equal to 1" in msg


def test_yaml_syntax_error_names_the_line(tmp_path):
    path = write(tmp_path, "name: t\ngrid:\n  arch: [baseline\n  rot_loss: ce\n")
    with pytest.raises(ConfigError, match=rf"{path}:\d+: YAML syntax error"):
        C.load_config(path)


def test_set_errors_name_the_override(tmp_path):
    path = write(tmp_path, "name: t\n")
    with pytest.raises(ConfigError, match=r"--set train.lrr=1: train.lrr: unknown key 'lrr'"):
        C.load_config(path, overrides=["train.lrr=1"])
    with pytest.raises(ConfigError, match="expected key.path=value"):
        C.load_config(path, overrides=["train.lr"])
    with pytest.raises(ConfigError, match="no such profile .available: none defined"):
        C.load_config(path, profile="gpu")


def test_missing_file_and_non_mapping(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        C.load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="expected a mapping"):
        C.load_config(write(tmp_path, "- a\n- b\n"))


def test_cells_are_frozen_hashable_and_keyed_stably(tmp_path):
    path = write(tmp_path, "name: t\ngrid: {folds: [p01]}\n")
    cells = C.expand_grid(C.load_config(path), patients=["p00", "p01"])
    assert len(cells) == 5 * 3 * 2 * 3  # arch x rot_loss x (personalized, cross-subject p01) x seeds 0-2
    with pytest.raises(Exception):
        cells[0].arch = "lstm"  # type: ignore[misc]
    assert len(set(cells)) == len(cells)
    # same config in another process -> same keys
    code = (
        "import json,sys; from bronchocli import config as C; "
        f"print(json.dumps([c.key for c in C.expand_grid(C.load_config({str(path)!r}), ['p00','p01'])]))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert json.loads(out) == [c.key for c in cells]


def test_a_run_relevant_change_changes_the_key_and_tracking_does_not(tmp_path):
    base = C.load_config(write(tmp_path, "name: t\ngrid: {folds: [p00]}\n"))
    key = C.expand_grid(base, ["p00"])[0].key
    assert base.train.lr != 5e-4
    assert C.expand_grid(base.with_values({"train.lr": 5e-4}), ["p00"])[0].key != key
    assert C.expand_grid(base.with_values({"runs.uri": "http://x:5000"}), ["p00"])[0].key == key


def test_cross_subject_folds(tmp_path):
    cfg = C.load_config(write(tmp_path, "name: t\ngrid: {population: cross-subject, arch: lstm, rot_loss: ce, seed: 0}\n"))
    assert [c.fold for c in C.expand_grid(cfg, ["a", "b", "c"])] == ["a", "b", "c"]
    with pytest.raises(ConfigError, match="needs the dataset's patient list"):
        C.expand_grid(cfg)
    listed = cfg.with_values({"grid.folds": ["zz"]})
    with pytest.raises(ConfigError, match=r"\['zz'\] not in the dataset's patients"):
        C.expand_grid(listed, ["a", "b"])


def test_speed_only_settings_do_not_change_the_key(tmp_path):
    base = C.load_config(write(tmp_path, "name: t\ngrid: {folds: [p00]}\n"))
    key = C.expand_grid(base, ["p00"])[0].key
    fast = base.with_values({"train.threads": 7, "data.workers": 0, "data.cache_dir": "/elsewhere"})
    assert C.expand_grid(fast, ["p00"])[0].key == key


def test_empty_grid_axes_and_bad_training_sizes_are_rejected(tmp_path):
    path = write(tmp_path, """\
        name: t
        grid:
          arch: []
          seed: [0, 0]
          train_trajectories: [0, 2]
        train:
          batch_size: 4
          effective_batch: 10
        """)
    with pytest.raises(ConfigError) as exc:
        C.load_config(path)
    msg = str(exc.value)
    assert "4 problems" in msg
    assert f"{path}:3: grid.arch: []: " in msg and "must list at least one value" in msg
    assert f"{path}:4: grid.seed: " in msg and "lists a value twice" in msg
    assert f"{path}:5: grid.train_trajectories: " in msg and "every value must be in [1, 10000]" in msg
    assert "effective_batch (10) must be a multiple of batch_size (4)" in msg


def test_the_train_trajectories_axis_multiplies_the_grid(tmp_path):
    cfg = C.load_config(write(tmp_path, """\
        name: t
        grid: {arch: baseline, rot_loss: mse, population: personalized, seed: 0, train_trajectories: [2, null]}
        """))
    cells = C.expand_grid(cfg, ["p00"])
    assert [c.label for c in cells] == ["baseline/mse/personalized/s0/world/t2", "baseline/mse/personalized/s0/world"]
    assert cells[0].key != cells[1].key


def test_eval_thresholds_are_validated_and_reach_the_evaluation(tmp_path):
    from bronchocli.training.evaluate import thresholds

    path = write(tmp_path, "name: t\neval:\n  ctf_angle: 200\n  rpe_gap: 0\n  ctf_pos: 3\n")
    with pytest.raises(ConfigError) as exc:
        C.load_config(path)
    msg = str(exc.value)
    assert "3 problems" in msg
    assert f"{path}:3: eval.ctf_angle: 200" in msg and f"{path}:4: eval.rpe_gap: 0" in msg
    assert "eval.ctf_pos: unknown key 'ctf_pos' (allowed: ctf_angle, ctf_position, ctf_position_mm, rpe_gap)" in msg
    cfg = C.load_config(write(tmp_path, "name: t\n"), overrides=["eval.ctf_position=2.5", "eval.rpe_gap=4"])
    t = thresholds(cfg.eval)
    assert (t.position, t.position_mm, t.angle, t.gap) == (2.5, 5.0, 10.0, 4)
    assert C.cell_key(cfg, {"arch": "lstm"}) == C.cell_key(C.load_config(write(tmp_path, "name: t\n")),
                                                          {"arch": "lstm"})  # thresholds do not retrain


# -- no renamed keys: 0.1.0 has had no release, so an old section name is an unknown key ------------------------


def test_the_old_section_names_are_unknown_keys(tmp_path):
    """``tracking`` (now ``runs``) and ``slurm`` (now ``sweep.launchers.slurm``) are refused like any unknown key,
    naming the line and the allowed sections: nothing reads them as the new ones."""
    path = write(tmp_path, "name: t\ntracking: {uri: sqlite:///old.db}\n")
    with pytest.raises(ConfigError, match=rf"{path}:2: tracking: unknown key 'tracking' \(allowed: .*runs"):
        C.load_config(path)
    with pytest.raises(ConfigError, match=r"--set slurm.partition=gpu: slurm: unknown key 'slurm'"):
        C.load_config(write(tmp_path, "name: t\n"), overrides=["slurm.partition=gpu"])


def test_paper_profile_follows_the_authors_code_where_the_text_differs(repo):
    """docs/reproduction.md: organize.py --length 10 cuts 10 frames = 9 pairs; train_all.sh's --intra-patient
    draws 15 trajectories and splits them 80/20 = 12 train + 3 validation; 512 windows per optimiser step."""
    cfg = C.load_config(repo / "experiments.yaml", "paper")
    assert cfg.data.window == 9 and cfg.data.overlap == 0  # consecutive windows share one frame, as theirs
    assert cfg.train.batch_size == 4 * 9 and cfg.train.effective_batch == 512 * 9 == 4608
    assert (cfg.splits.train, cfg.splits.val, cfg.splits.test) == (12, 3, 3)
    assert cfg.dataset.generate.trajectories == 12 + 3 + 3


STAGED = """\
    name: t
    grid: {arch: [baseline], rot_loss: [mse], population: [personalized], seed: [0]}
    stages:
      - {name: a, grid: {arch: [lstm]}}
      - {name: b, select: {top: 1}, grid: {population: [cross-subject], folds: [p00]}}
"""


def test_a_set_grid_field_the_stages_decide_is_refused_or_warned_never_dropped(tmp_path, caplog):
    path = write(tmp_path, STAGED)
    # arch: stage a's own grid sets it, stage b takes it from a's selection: the --set would change nothing
    with pytest.raises(ConfigError, match=r"--set grid.arch=\[conv3d\]: has no effect: the stages decide the cells "
                                          r"and every stage sets arch itself \(a: its grid sets arch; b: selected "
                                          r"from the previous stage\)"):
        C.load_config(path, overrides=["grid.arch=[conv3d]"])
    with pytest.raises(ConfigError, match="--set grid={arch: \\[conv3d\\]}: has no effect"):  # the whole grid, too
        C.load_config(path, overrides=["grid={arch: [conv3d]}"])
    # rot_loss: stage a reads the top-level grid, stage b its selection: applied, with one warning saying so
    with caplog.at_level("WARNING", logger="bronchocli.config.loading"):
        cfg = C.load_config(path, overrides=["grid.rot_loss=[ce]"])
    assert cfg.stages[0].stage_grid(cfg.grid).rot_loss == ["ce"]
    (record,) = caplog.records
    assert record.getMessage() == ("--set grid.rot_loss=[ce]: applies to stage(s) a only; the others set rot_loss "
                                   "themselves (b: selected from the previous stage)")
    caplog.clear()
    with caplog.at_level("WARNING", logger="bronchocli.config.loading"):  # seed: every stage reads it
        cfg = C.load_config(path, overrides=["grid.seed=[1,2]"])
    assert not caplog.records and cfg.stages[1].stage_grid(cfg.grid).seed == [1, 2]
    assert C.load_config(write(tmp_path, "name: t\n"), overrides=["grid.arch=[conv3d]"]).grid.arch == ["conv3d"]


# -- issue 40.2: enum-like values written the common ways ---------------------------------------------------------

SPELLINGS = [  # (key, as written in YAML, canonical value)
    ("train.precision", "32", "32"), ("train.precision", "32.0", "32"), ("train.precision", "fp32", "32"),
    ("train.precision", "FP32", "32"), ("train.precision", "32-true", "32"), ("train.precision", "16", "16-mixed"),
    ("train.precision", "fp16", "16-mixed"), ("train.precision", "half", "16-mixed"),
    ("train.precision", "bf16", "bf16-mixed"), ("train.precision", "BF16_Mixed", "bf16-mixed"),
    ("train.precision", "bfloat16", "bf16-mixed"), ("train.precision", "'32'", "32"),
    ("runs.model_artifact", "16", "fp16"), ("runs.model_artifact", "float32", "fp32"),
    ("runs.model_artifact", "NONE", "none"), ("data.frames_on_device", "yes", "yes"),
    ("data.frames_on_device", "no", "no"), ("data.frames_on_device", "Auto", "auto"),
    ("model.channels_last", "AUTO", "auto"), ("model.channels_last", "true", True),
    ("train.compile", "reduce_overhead", "reduce-overhead"), ("train.compile", "false", False),
    ("train.device", "CUDA", "cuda"), ("train.schedule", "Cosine", "cosine"),
    ("dataset.csv.angle_units", "degrees", "deg"), ("dataset.csv.position_units", "millimetres", "mm"),
    ("dataset.csv.camera_forward", "+Z", "z"), ("dataset.csv.camera_up", "-Y", "-y"),
    ("dataset.format", "CSV", "csv"), ("tune.pruner", "None", "none"), ("sweep.launcher", "Slurm", "slurm"),
    ("grid.population", "[Cross_Subject, personalised]", ["cross-subject", "personalized"]),
    ("grid.arch", "[ConvLSTM, Conv3D, offset-net]", ["convlstm", "conv3d", "offsetnet"]),
    ("grid.rot_loss", "[MSE]", ["mse"]), ("grid.pose_frame", "Camera", ["camera"]),
    ("dataset.generate.lobes", "[UR, bl]", ["ur", "bl"]),
]


@pytest.mark.parametrize("key, written, canonical", SPELLINGS, ids=[f"{k}={w}" for k, w, _ in SPELLINGS])
def test_enum_values_written_the_common_ways_read_as_the_canonical_one(tmp_path, key, written, canonical):
    leaf, extra = written, []
    if key.startswith("dataset.csv.camera"):  # the two axes must differ
        other = "camera_up" if key.endswith("forward") else "camera_forward"
        leaf, extra = f"{written}, {other}: x", [f"dataset.csv.{other}=x"]

    def flow(parts: list[str]) -> str:  # a.b.c -> "a: {b: {c: <written>}}"
        return f"{parts[0]}: {leaf}" if len(parts) == 1 else f"{parts[0]}: {{{flow(parts[1:])}}}"

    yaml_text = f"name: t\n{flow(key.split('.'))}\n"
    for cfg in (C.load_config(write(tmp_path, yaml_text)), C.load_config(write(tmp_path, "name: t\n"),
                                                                            overrides=[f"{key}={written}", *extra])):
        value = cfg
        for part in key.split("."):
            value = getattr(value, part)
        assert value == canonical, (key, written, value)


def test_precision_32_as_a_yaml_number_is_fp32_in_the_resolved_config(tmp_path):
    cfg = C.load_config(write(tmp_path, "name: t\ntrain: {precision: 32}\n"))
    assert cfg.train.precision == "32" and "precision: '32'" in cfg.to_yaml()
    assert C.load_config(write(tmp_path, "name: t\n"), overrides=["train.precision=32"]).train.precision == "32"
    # the canonical value keys the cell: how it was written changes nothing
    a = C.load_config(write(tmp_path, "name: t\ntrain: {precision: fp32}\ngrid: {folds: [p00]}\n"))
    b = C.load_config(write(tmp_path, "name: t\ntrain: {precision: '32'}\ngrid: {folds: [p00]}\n"))
    assert C.expand_grid(a, ["p00"])[0].key == C.expand_grid(b, ["p00"])[0].key


@pytest.mark.parametrize("override, choices, spelling", [
    ("train.precision=64", "'auto', '32', '16-mixed' or 'bf16-mixed'", "32 as a number, fp32"),
    ("data.frames_on_device=maybe", "'auto', 'yes' or 'no'", "true"),
    ("model.channels_last=7", "'auto', true or false", "any case"),
    ("grid.arch=[lstm, transformer]", "'baseline', 'lstm', 'convlstm', 'conv3d' or 'offsetnet'", "any case"),
])
def test_an_unmatched_choice_is_one_line_naming_the_choices_and_spellings(tmp_path, override, choices, spelling):
    with pytest.raises(ConfigError) as info:
        C.load_config(write(tmp_path, "name: t\n"), overrides=[override])
    message = str(info.value)
    assert len(message.splitlines()) == 1 and f"must be one of {choices}" in message and spelling in message, message
    key = override.split("=")[0]
    assert f"--set {override}: {key}" in message, message
    if key == "grid.arch":
        assert 'grid.arch[1]: "transformer"' in message  # the item, not the list


def _enum_fields(model=C.Config, prefix: str = "") -> list[tuple[str, object]]:
    """(dotted path, annotation) of every setting whose annotation holds a Literal (in a union or a list)."""
    from typing import Annotated, Literal, Union, get_args, get_origin

    from pydantic import BaseModel

    def literal_in(a) -> bool:
        if get_origin(a) is Literal:
            return True
        if get_origin(a) is Annotated:
            return literal_in(get_args(a)[0])
        return any(literal_in(x) for x in get_args(a)) if get_origin(a) in (Union, __import__("types").UnionType,
                                                                               list) else False

    out = []
    for name, field in model.model_fields.items():
        ann = field.annotation
        for sub in [ann, *get_args(ann)]:
            if isinstance(sub, type) and issubclass(sub, BaseModel):
                out += _enum_fields(sub, f"{prefix}{name}.")
        if literal_in(ann) or name == "arch":
            out.append((f"{prefix}{name}", ann, list(field.metadata)))
    return out


def test_every_enum_like_setting_is_read_the_common_ways():
    """A new Literal setting joins the spellings (``spelled``), or this fails naming it."""
    from bronchocli.config.spellings import speller_of

    def spelled(ann, metadata) -> bool:
        from typing import get_args
        if speller_of(ann) or any(getattr(getattr(m, "func", None), "__class__", None).__name__ == "Speller"
                                  for m in metadata):
            return True
        return any(speller_of(a) for a in get_args(ann))  # list[spelled(...)]

    fields = _enum_fields() + [f for prefix, model in _launcher_models().items() for f in _enum_fields(model, prefix)]
    assert {"train.precision", "grid.arch", "data.frames_on_device", "stages.select.over",
            "sweep.launchers.slurm.on_time_limit"} <= {p for p, *_ in fields}
    missing = [p for p, ann, meta in fields if p != "grid.folds" and not spelled(ann, meta)]  # folds: patient names
    assert not missing, missing


# -- issue 37.4: every number has a documented range -------------------------------------------------------------

VALIDATED_RANGES = {  # bounded by a validator of their own (tuples, nullable lists): the range as documented
    "dataset.generate.step_mm": "(0, 100] each, min ≤ max", "dataset.csv.spacing_mm": "(0, 100] each",
    "grid.train_trajectories": "[1, 10000] each, or null",
}


def _launcher_models() -> dict[str, type]:
    """``sweep.launchers.<name>.`` -> the settings model of each launcher this package ships that has one (their
    own sections; a test's launcher registered meanwhile is not documented here)."""
    from bronchocli.sweep.launchers import launcher_class, names

    shipped = [launcher_class(n) for n in names() if launcher_class(n).__module__.startswith("bronchocli.")]
    return {f"sweep.launchers.{k.name}.": k.Settings for k in shipped if k.Settings}


def _numeric_settings(model=C.Config, prefix: str = "") -> list[str]:
    from typing import Annotated, Literal, Union, get_args, get_origin

    from pydantic import BaseModel

    def kinds(a) -> set:
        if get_origin(a) is Annotated:
            return kinds(get_args(a)[0])
        if get_origin(a) in (Union, __import__("types").UnionType, list, tuple):
            return set().union(*(kinds(x) for x in get_args(a)))
        return {a} if a in (int, float) else set()

    out = []
    for name, field in model.model_fields.items():
        ann, path = field.annotation, f"{prefix}{name}"
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            out += _numeric_settings(ann, f"{path}.")
        elif kinds(ann) and get_origin(ann) is not Literal:
            out.append(path)
    return out


def test_every_number_has_a_finite_range_documented_in_config_md(repo):
    from bronchocli.config.messages import allowed_range

    roots = {path: (C.Config, path) for path in _numeric_settings()}
    for prefix, model in _launcher_models().items():  # a launcher's own section: its model is the root
        roots.update({path: (model, path[len(prefix):]) for path in _numeric_settings(model, prefix)})
    settings = list(roots)
    assert {"train.steps", "train.batch_size", "train.effective_batch", "dataset.generate.patients",
            "dataset.generate.trajectories", "dataset.generate.workers", "data.workers", "data.image_size",
            "train.lr", "train.val_every", "grid.seed", "sweep.launchers.slurm.mem_gb"} <= set(settings)
    docs = (repo / "docs" / "config.md").read_text()
    table = dict(line.split(" | ")[:2] for line in docs.split("## Ranges", 1)[1].splitlines()
                 if line.startswith("| `"))
    table = {k.strip("|` "): v.strip(" |") for k, v in table.items()}
    for path in settings:
        root, sub = roots[path]
        documented = VALIDATED_RANGES.get(path) or allowed_range(root, tuple(sub.split(".")))
        assert documented is not None and "∞" not in documented, f"{path}: no upper or lower bound"
        assert table.get(path) == documented, f"docs/config.md, Ranges: {path} says {table.get(path)!r}, " \
                                              f"the schema {documented!r}"


@pytest.mark.parametrize("override, shown", [
    ("train.steps=100000000000000000000000000000000", "[1, 10000000]"),
    ("train.batch_size=100000000000000000000", "[1, 65536]"),
    ("train.effective_batch=2000000000", "[1, 1048576]"),
    ("dataset.generate.patients=1000000000000", "[1, 1000]"),
    ("dataset.generate.workers=100000000", "[1, 1024]"),
    ("dataset.generate.trajectories=100001", "[1, 10000]"),
    ("data.image_size=4096", "[16, 1024]"),
    ("train.lr=1000", "(0, 10]"),
    ("train.val_every=0", "[1, 10000000]"),
])
def test_a_number_out_of_its_range_is_one_line_naming_key_value_and_range(tmp_path, override, shown):
    key, value = override.split("=")
    with pytest.raises(ConfigError) as info:
        C.load_config(write(tmp_path, "name: t\n"), overrides=[override])
    message = str(info.value)
    assert len(message.splitlines()) == 1 and f"{key}: {value}: " in message, message
    assert f"(allowed range {shown})" in message, message


def test_the_ranges_admit_every_shipped_config_and_the_paper_scale(repo):
    """The bounds are generous: the paper's profile (4,608 pairs per step, 256² frames) is well inside them."""
    cfg = C.load_config(repo / "experiments.yaml", "paper")
    assert cfg.train.pairs_per_step == 4608 and cfg.data.image_size in (None, 256)
    C.load_config(repo / "experiments.yaml", overrides=["train.steps=10000000", "train.batch_size=65536",
                                                        "train.effective_batch=1048576", "train.lr=10"])


def test_the_learning_cost_profile_searches_the_cost_of_bronchotrack_from_todays_recipe(repo):
    """Issue 45: the tuner searches the cost of learning (pairs to val ratio 0.90) of BronchoTrack at 96², every
    trial within the same budget of pairs, starting from today's hyperparameters; a key enqueued outside the
    space is refused."""
    cfg = C.load_config(repo / "experiments.yaml", "learning-cost")
    assert cfg.tune.objective == "cost" and cfg.tune.budget_pairs == cfg.train.steps * cfg.train.batch_size
    assert (cfg.grid.arch, cfg.grid.rot_loss, cfg.dataset.generate.image_size) == (["convlstm"], ["ce"], 96)
    assert cfg.train.threads == 1 and cfg.train.val_every * cfg.train.batch_size == 1000
    (first,) = cfg.tune.enqueue
    default = C.load_config(repo / "experiments.yaml", "bronchotrack-cpu")  # the measured reference recipe
    assert first == {"train.lr": default.train.lr, "train.warmup": default.train.warmup,
                     "train.batch_size": default.train.batch_size, "model.dropout": default.model.dropout}
    assert set(first) <= set(cfg.tune.space)
    with pytest.raises(ConfigError, match=r"enqueue\[0\]: train.bogus not in tune.space"):
        C.load_config(repo / "experiments.yaml", "learning-cost", overrides=["tune.enqueue=[{train.bogus: 1}]"])


@pytest.mark.parametrize("enqueue, message", [
    ("[{train.lr: 0.5}]", r"tune.enqueue\[0\].train.lr: 0.5: must be a number within tune.space.train.lr's range "
                          r"\[0.0003, 0.003\]"),
    ("[{train.lr: 1.0e-3}, {train.batch_size: 25}]",
     r"tune.enqueue\[1\].train.batch_size: 25: must be one of tune.space.train.batch_size's choices \(10, 20, 40\)"),
    ("[{train.lr: abc}]", r"tune.enqueue\[0\].train.lr: 'abc': must be a number"),
    ("[{model.dropout: true}]", r"tune.enqueue\[0\].model.dropout: True: must be a number"),
])
def test_every_enqueued_trial_meets_the_rules_a_trial_meets_when_the_config_loads(repo, enqueue, message):
    """Issue 60: a recipe Optuna would refuse (a choice not in the space) or that lies outside the searched range
    fails at load (`bronchopose config`), in one line naming the trial and the key, not as a failed trial."""
    with pytest.raises(ConfigError, match=message) as info:
        C.load_config(repo / "experiments.yaml", "learning-cost", overrides=[f"tune.enqueue={enqueue}"])
    assert len(str(info.value).splitlines()) == 1


def test_an_enqueued_trial_whose_config_is_invalid_is_refused_naming_the_trial(tmp_path):
    path = tmp_path / "experiments.yaml"
    path.write_text("name: t\ntune:\n  space:\n    train.batch_size: {type: int, low: 1, high: 64}\n"
                    "  enqueue:\n    - {train.batch_size: 8}\n    - {train.batch_size: 7.5}\n")
    with pytest.raises(ConfigError, match=r"tune.enqueue\[1\].train.batch_size: 7.5: must be a whole number"):
        C.load_config(path)
    # each value alone is one the space takes; together they make a config no trial could train with
    path.write_text("name: t\ntrain: {batch_size: 4, effective_batch: 8}\ntune:\n  space:\n"
                    "    train.batch_size: {type: categorical, choices: [4, 8]}\n"
                    "    train.effective_batch: {type: categorical, choices: [8, 12]}\n"
                    "  enqueue:\n    - {train.batch_size: 8, train.effective_batch: 12}\n")
    with pytest.raises(ConfigError, match=r"tune.enqueue\[0\] \(trial 0\): .*effective_batch \(12\) must be a "
                                          r"multiple of batch_size") as info:
        C.load_config(path)
    assert len(str(info.value).splitlines()) == 1


def test_the_cpu_study_is_the_papers_personalized_grid_at_the_recipe_the_cost_study_measured(repo):
    """Issue 45.3: Tables 2-3's grid (4 architectures x 3 rotation losses, personalized, >= 2 seeds), every cell at
    one budget, with the hyperparameters of the learning-cost study's first trial on a schedule that spans it."""
    cfg = C.load_config(repo / "experiments.yaml", "cpu-study")
    cells = C.expand_grid(cfg, patients=["p00", "p01", "p02"])
    assert {(c.arch, c.rot_loss) for c in cells} == {(a, r) for a in ("baseline", "lstm", "convlstm", "conv3d")
                                                     for r in ("mse", "de", "ce")}
    assert {c.population for c in cells} == {"personalized"} and len({c.seed for c in cells}) >= 2
    assert len(cells) == 12 * len({c.seed for c in cells})
    (recipe,) = C.load_config(repo / "experiments.yaml", "learning-cost").tune.enqueue
    assert recipe == {"train.lr": cfg.train.lr, "train.warmup": cfg.train.warmup,
                      "train.batch_size": cfg.train.batch_size, "model.dropout": cfg.model.dropout}
    assert cfg.train.schedule == "cosine" and cfg.train.steps * cfg.train.pairs_per_step == 10_000
    assert cfg.dataset.generate.image_size == 96 and cfg.train.threads == 1
