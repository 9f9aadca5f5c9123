"""The one cell type: validation at every door (grid, flags, tags, --only), labels, tags round trip."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bronchocli import cells
from bronchocli.cells import POPULATIONS, POSE_FRAMES, Cell, parse_only, select
from bronchocli.config import Config, expand_grid
from bronchocli.errors import ConfigError
from bronchocli.registry import arch_names, rot_loss_names

CFG = Config.model_validate({"name": "t", "grid": {"folds": ["p00", "p01"], "seed": [0]}})
CELLS = expand_grid(CFG, ["p00", "p01", "p02"])  # 5 archs x 3 losses x (personalized + 2 folds) = 45


@pytest.mark.parametrize("values, message", [
    ({"arch": "resnet", "rot_loss": "ce", "population": "personalized"}, "arch 'resnet': must be one of baseline"),
    ({"arch": "lstm", "rot_loss": "l1", "population": "personalized"}, "rot_loss 'l1': must be one of mse, de, ce"),
    ({"arch": "lstm", "rot_loss": "ce", "population": "personalized", "pose_frame": "foo"},
     "pose_frame 'foo': must be one of world, camera"),
    ({"arch": "lstm", "rot_loss": "ce", "population": "cross-subject"}, "fold: cross-subject needs"),
    ({"arch": "lstm", "rot_loss": "ce", "population": "personalized", "fold": "p00"}, "only cross-subject cells"),
    ({"arch": "lstm", "rot_loss": "ce", "population": "personalized", "seed": "x"}, "seed 'x': must be an integer"),
    ({"arch": "lstm", "rot_loss": "ce", "population": "personalized", "train_trajectories": 0},
     "train_trajectories 0"),
])
def test_a_bad_cell_is_one_line_naming_the_field(values, message):
    with pytest.raises(ConfigError) as exc:
        cells.make(**values)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_a_cell_without_a_pose_frame_takes_the_configs_first_one():
    camera_first = Config.model_validate({"name": "t", "grid": {"pose_frame": ["camera", "world"]}})
    coords = {"arch": "lstm", "rot_loss": "ce", "population": "personalized"}
    assert camera_first.cell(**coords).pose_frame == "camera"
    assert camera_first.cell(**coords, pose_frame=None).pose_frame == "camera"
    assert camera_first.cell(**coords, pose_frame="world").pose_frame == "world"
    assert CFG.cell(**coords).pose_frame == "world"  # the schema's default grid


def test_tags_round_trip_and_label():
    cell = CFG.cell(arch="convlstm", rot_loss="ce", population="cross-subject", fold="p01", seed=3,
                    pose_frame="camera", train_trajectories=4)
    assert cell.label == "convlstm/ce/cross-subject/p01/s3/camera/t4"
    back = Cell.from_tags({**cell.tags(), "cell_key": cell.key})
    assert back == cell and back.key == cell.key and len(cell.key) == 16
    assert cell.tags()["fold"] == "p01" and CFG.cell(arch="lstm", rot_loss="ce", population="personalized").tags()[
        "fold"] == ""


def test_the_key_depends_on_the_run_config_not_on_speed_settings():
    a = CFG.cell(arch="lstm", rot_loss="ce", population="personalized")
    assert CFG.with_values({"train.threads": 3}).cell(**a.coords()).key == a.key
    assert CFG.with_values({"train.lr": 0.5}).cell(**a.coords()).key != a.key
    assert CFG.cell(**{**a.coords(), "seed": 1}).key != a.key


def test_only_filters_are_anded_and_values_ored():
    only = parse_only(["arch=lstm,conv3d;population=cross-subject", "fold=p01"])
    assert only == {"arch": {"lstm", "conv3d"}, "population": {"cross-subject"}, "fold": {"p01"}}
    chosen = select(CELLS, only)
    assert len(chosen) == 2 * 3 and {(c.arch, c.fold) for c in chosen} == {("lstm", "p01"), ("conv3d", "p01")}
    assert select(CELLS, parse_only(["rot-loss=ce", "seed=0"])) == [c for c in CELLS if c.rot_loss == "ce"]
    assert select(CELLS, parse_only(["arch=lstm,baseline", "arch=lstm"])) == [c for c in CELLS if c.arch == "lstm"]
    assert select(CELLS, {}) == CELLS


@pytest.mark.parametrize("spec, message", [
    ("colour=red", "key one of arch"),
    ("arch", "expected key=value"),
    ("arch=", "no values"),
    ("arch=resnet", "arch 'resnet' must be one of"),
    ("seed=one", "seed 'one': must be an integer"),
])
def test_malformed_only_is_rejected(spec, message):
    with pytest.raises(ConfigError, match=message):
        parse_only([spec])


def test_an_unknown_value_names_what_the_plan_has():
    with pytest.raises(ConfigError, match=r"fold=p07: .*it has: p00, p01"):
        select(CELLS, parse_only(["fold=p07"]))


VALUES = {"arch": arch_names(), "rot_loss": rot_loss_names(), "population": POPULATIONS, "pose_frame": POSE_FRAMES}


@given(st.dictionaries(st.sampled_from(sorted(VALUES)), st.sets(st.integers(0, 4), min_size=1), min_size=1),
       st.booleans())
def test_only_parses_any_well_formed_selection_back_to_itself(picks, separate):
    wanted = {k: {VALUES[k][i % len(VALUES[k])] for i in idx} for k, idx in picks.items()}
    parts = [f"{k}={','.join(sorted(v))}" for k, v in wanted.items()]
    specs = parts if separate else [";".join(parts)]
    assert parse_only(specs) == wanted


@given(st.text(max_size=30))
def test_only_never_raises_anything_but_a_config_error(text):
    try:
        parse_only([text])
    except ConfigError:
        pass
