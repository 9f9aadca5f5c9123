"""Populations: splits are leak-free, match the configured counts, and are the same in every process."""

from __future__ import annotations

import os
import subprocess
import sys
from collections import Counter

import pandas as pd
import pytest
from tinydata import write_tiny_dataset

from bronchocli import cells
from bronchocli.config import Splits
from bronchocli.data.reader import open_dataset_dir
from bronchocli.data.splits import POPULATIONS, limit_train, make_split, personalized_counts, read_manifest
from bronchocli.errors import ConfigError, DataError

CPU = Splits(train=4, val=1, test=1, cross_subject_val=1)


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    return open_dataset_dir(write_tiny_dataset(tmp_path_factory.mktemp("splits") / "ds"))


def assert_disjoint(split):
    keys = [t.key for part in split.parts().values() for t in part]
    assert len(keys) == len(set(keys)), "a trajectory is in two splits"
    frames = [set(split.frame_indices(p)) for p in ("train", "val", "test")]
    assert not (frames[0] & frames[1]) and not (frames[0] & frames[2]) and not (frames[1] & frames[2])


def per_group(trajs) -> Counter:
    return Counter((t.patient, t.lobe) for t in trajs)


def test_registry_matches_the_config_names():
    assert tuple(POPULATIONS) == cells.POPULATIONS == ("personalized", "cross-subject")


@pytest.mark.parametrize("counts", [(4, 1, 1), (2, 2, 1), (1, 1, 1)])
def test_personalized_is_disjoint_with_the_configured_counts(ds, counts):
    split = make_split(ds, "personalized", None, Splits(train=counts[0], val=counts[1], test=counts[2]))
    assert_disjoint(split)
    groups = {(p, lb) for p in ds.patients for lb in ds.lobes}
    for part, want in zip(("train", "val", "test"), counts):
        assert per_group(split.parts()[part]) == {g: want for g in groups}
    m = split.manifest()
    assert list(m.columns) == ["patient", "lobe", "trajectory", "split"]
    assert set(m.split) == {"train", "val", "test"} and len(m) == 12 * sum(counts)
    if sum(counts) < 6:
        assert any("unused" in n for n in split.notes)


def test_personalized_falls_back_in_proportion_and_refuses_too_few(ds, tmp_path):
    split = make_split(ds, "personalized", None, Splits())  # paper's 15/3/3 on 6 trajectories
    assert_disjoint(split)
    assert [len(split.train), len(split.val), len(split.test)] == [12 * 4, 12, 12]
    note = "p00/ur, p00/br, p00/ul, p00/bl and 8 more: 6 trajectories -> train/val/test 4/1/1 (fewer than the "
    assert split.notes == (note + "configured 15/3/3)",)
    small = open_dataset_dir(write_tiny_dataset(tmp_path / "two", patients=1, lobes=("ul",), trajectories=2,
                                                frames=3, image_size=16))
    with pytest.raises(DataError, match=r"p00/ul has 2 trajectories; at least 3 are needed"):
        make_split(small, "personalized", None, Splits())


@pytest.mark.parametrize("n, want, expected", [
    (21, (15, 3, 3), (15, 3, 3)), (30, (15, 3, 3), (15, 3, 3)), (6, (15, 3, 3), (4, 1, 1)),
    (3, (15, 3, 3), (1, 1, 1)), (14, (15, 3, 3), (10, 2, 2)), (13, (15, 3, 3), (11, 1, 1)), (20, (15, 3, 3), (16, 2, 2)),
    (50, (1, 100, 1), (1, 48, 1)), (4, (1, 1, 5), (1, 1, 2)),
])
def test_personalized_count_rule(n, want, expected):
    got = personalized_counts(n, *want, where="p/l")
    assert got == expected and sum(got) <= n and min(got) >= 1


@pytest.mark.parametrize("fold", ["p00", "p01", "p02"])
def test_cross_subject_keeps_the_test_patient_out_of_train_and_val(ds, fold):
    split = make_split(ds, "cross-subject", fold, CPU)
    assert_disjoint(split)
    assert {t.key for t in split.test} == {t.key for t in ds.of(patient=fold)}
    seen = set(split.frame_indices("train")) | set(split.frame_indices("val"))
    test_patient_frames = set(ds.frames.index[ds.frames.patient == fold])
    assert not seen & test_patient_frames
    others = {(p, lb) for p in ds.patients if p != fold for lb in ds.lobes}
    assert per_group(split.val) == {g: 1 for g in others}
    assert per_group(split.train) == {g: 5 for g in others}
    assert split.manifest().groupby("split").size().to_dict() == {"train": 40, "val": 8, "test": 24}


def test_bad_population_and_fold_are_clear_errors(ds):
    with pytest.raises(ConfigError, match=r"'leave-two-out': must be one of personalized, cross-subject"):
        make_split(ds, "leave-two-out", None, CPU)
    with pytest.raises(ConfigError, match=r"fold 'p09' is not a patient .* one of p00, p01, p02"):
        make_split(ds, "cross-subject", "p09", CPU)
    with pytest.raises(ConfigError, match=r"cross-subject needs a fold"):
        make_split(ds, "cross-subject", None, CPU)
    with pytest.raises(ConfigError, match=r"personalized takes no fold"):
        make_split(ds, "personalized", "p00", CPU)


def test_seed_changes_the_split(ds):
    a = make_split(ds, "personalized", None, CPU).manifest()
    b = make_split(ds, "personalized", None, Splits(train=4, val=1, test=1, seed=1)).manifest()
    assert not a.equals(b)


_CHILD = """
import sys
from bronchocli.config import Splits
from bronchocli.data.reader import open_dataset_dir
from bronchocli.data.splits import make_split
ds = open_dataset_dir(sys.argv[1])
s = Splits(train=4, val=1, test=1, cross_subject_val=1, seed=7)
make_split(ds, "personalized", None, s).write_manifest(sys.argv[2])
make_split(ds, "cross-subject", "p01", s).write_manifest(sys.argv[3])
"""


def test_same_split_in_another_process(ds, tmp_path):
    s = Splits(train=4, val=1, test=1, cross_subject_val=1, seed=7)
    mine = [make_split(ds, "personalized", None, s), make_split(ds, "cross-subject", "p01", s)]
    paths = [tmp_path / "personalized.csv", tmp_path / "cross.csv"]
    env = {**os.environ, "PYTHONHASHSEED": "12345"}  # Python's hash() differs; our split must not
    subprocess.run([sys.executable, "-c", _CHILD, str(ds.root), *map(str, paths)], check=True, env=env)
    for split, path in zip(mine, paths):
        theirs = read_manifest(path)
        pd.testing.assert_frame_equal(theirs, split.manifest().astype(str))
    assert not list(tmp_path.glob(".*.tmp"))  # written atomically, nothing left behind


@pytest.mark.parametrize("population, fold", [("personalized", None), ("cross-subject", "p01")])
def test_limit_train_keeps_nested_subsets_per_group_and_leaves_val_and_test(ds, population, fold):
    split = make_split(ds, population, fold, CPU)
    assert limit_train(split, None, 0) is split
    full = per_group(split.train)
    kept = {n: limit_train(split, n, 0) for n in (1, 2, 3)}
    for n, small in kept.items():
        assert per_group(small.train) == {g: min(n, c) for g, c in full.items()}
        assert small.val == split.val and small.test == split.test and small.population == population
        assert small.fold == fold
        assert [t.key for t in small.train] == [t.key for t in split.train if t in small.train]  # order kept
        assert_disjoint(small)
    assert {t.key for t in kept[1].train} < {t.key for t in kept[2].train} < {t.key for t in kept[3].train}
    again = limit_train(make_split(ds, population, fold, CPU), 2, 0)
    assert [t.key for t in again.train] == [t.key for t in kept[2].train]  # deterministic
    other = [limit_train(split, 2, s) for s in range(1, 6)]
    assert any([t.key for t in o.train] != [t.key for t in kept[2].train] for o in other)  # the seed matters
    many = limit_train(split, max(full.values()) + 1, 0)
    assert per_group(many.train) == full and any("fewer than train_trajectories" in n for n in many.notes)
    assert not any("fewer than train_trajectories" in n for n in kept[1].notes)
