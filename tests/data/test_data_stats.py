"""`bronchopose data stats` end to end: the summary, per-split counts and the manifest it writes."""

from __future__ import annotations

import re

import pandas as pd
import pytest
import typer
from tinydata import turning_angles as turning
from tinydata import write_tiny_dataset
from typer.testing import CliRunner

from bronchocli.commands import data
from bronchocli.errors import BronchoError

# Mounted as the CLI mounts it (`bronchopose data ...`), whatever cli.py registers today.
app = typer.Typer()
app.add_typer(data.app, name="data")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("stats") / "ds", frames=6, image_size=16)


def run(*args: str, cwd=None) -> tuple[int, str, BaseException | None]:
    result = CliRunner().invoke(app, ["data", *args], env={"COLUMNS": "200"})
    if result.exception is not None and not isinstance(result.exception, (SystemExit, BronchoError)):
        raise result.exception
    return result.exit_code, result.stdout, result.exception


def write_config(tmp_path, root) -> str:
    path = tmp_path / "exp.yaml"
    path.write_text(f"name: t\ndataset: {{root: {root}}}\n"
                    "splits: {train: 4, val: 1, test: 1, cross_subject_val: 1}\ndata: {window: 2, overlap: 1}\n")
    return str(path)


def test_summary_of_a_dataset(tiny, tmp_path):
    code, out, _ = run("stats", "--config", write_config(tmp_path, tiny))  # DATASET from dataset.root
    assert code == 0
    fingerprint = (tiny / "dataset.json").read_text().split('"fingerprint": "')[1][:64]
    assert fingerprint in out and "16x16" in out
    assert re.search(r"p02\s*│\s*bl\s*│\s*6\s*│\s*36\s*│\s*30\s*│", out)  # trajectories, frames, pairs
    assert "rx" in out and "step (voxels/pair)" in out


def test_cross_subject_counts_and_manifest(tiny, tmp_path):
    manifest = tmp_path / "out" / "split.csv"
    code, out, _ = run("stats", str(tiny), "--population", "cross-subject", "--fold", "p01",
                       "--manifest", str(manifest), "--config", write_config(tmp_path, "elsewhere"))
    assert code == 0
    # train: 2 patients x 4 lobes x 5 trajectories of 6 frames; windows of 2 pairs with overlap 1: 4 each
    assert re.search(r"train\s*│\s*2\s*│\s*40\s*│\s*240\s*│\s*200\s*│\s*160", out)
    assert re.search(r"test\s*│\s*1\s*│\s*24\s*│\s*144\s*│\s*120\s*│\s*96", out)
    m = pd.read_csv(manifest, dtype=str)
    assert list(m.columns) == ["patient", "lobe", "trajectory", "split"] and len(m) == 72
    assert set(m[m.split == "test"].patient) == {"p01"} and "p01" not in set(m[m.split != "test"].patient)


def test_defaults_apply_without_a_config_file(tiny, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # no experiments.yaml here
    code, out, _ = run("stats", str(tiny), "--population", "personalized")
    assert code == 0
    assert "note: p00/ur, p00/br, p00/ul, p00/bl and 8 more: 6 trajectories -> train/val/test 4/1/1" in out  # the paper's 15/3/3, scaled down


@pytest.mark.parametrize("args, message", [
    (["--manifest", "m.csv"], "--manifest needs --population"),
    (["--population", "cross-subject", "--fold", "p7"], "fold 'p7' is not a patient"),
    (["--population", "cross-subject"], "cross-subject needs a fold"),
])
def test_bad_flags_are_clear_errors(tiny, tmp_path, args, message):
    _, _, exc = run("stats", str(tiny), "--config", write_config(tmp_path, tiny), *args)
    assert isinstance(exc, BronchoError) and message in str(exc)


def test_an_unknown_population_is_one_line(cli, tiny, tmp_path):  # a choice flag: checked before the command runs
    code, _, err = cli("data", "stats", str(tiny), "--config", write_config(tmp_path, tiny), "--population", "intra")
    assert code == 2 and "--population 'intra': must be one of personalized, cross-subject" in err
    assert len(err.strip().splitlines()) == 1


def test_missing_dataset_is_a_clear_error(tmp_path):
    _, _, exc = run("stats", str(tmp_path / "nope"), "--config", write_config(tmp_path, tmp_path))
    assert isinstance(exc, BronchoError) and "dataset directory not found" in str(exc)


def test_stats_names_trajectories_near_gimbal_lock(tmp_path):
    root = write_tiny_dataset(tmp_path / "ds", patients=1, lobes=("ur",), trajectories=2, frames=12, image_size=16)
    table = pd.read_csv(root / "p00.csv")
    first = table["trajectory"].astype(str) == str(table["trajectory"].iat[0])
    table.loc[first, ["Rx", "Ry", "Rz"]] = turning(-88.9, int(first.sum()))
    table.to_csv(root / "p00.csv", index=False)
    code, out, _ = run("stats", str(root))
    assert code == 0
    flat = " ".join(out.split())
    assert "world-frame labels near gimbal lock" in flat
    assert f"p00/ur/{table['trajectory'].iat[0]}" in flat and f"p00/ur/{table['trajectory'].iat[-1]}" not in flat
