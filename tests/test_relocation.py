"""Relocatable projects: MLflow keeps absolute artifact locations, yet a copied (``cp -a``) or moved project
writes and reads only its own store, and ``--set runs.artifacts=...`` takes effect or is refused in one line."""

from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path

import pytest
from tinydata import write_tiny_dataset
from tinyproject import write_config

from bronchocli.config import load_config
from bronchocli.runs.client import client_for, experiment_id
from bronchocli.runs.records import search_runs
from bronchocli.runs.relocation import _local_path, moved_roots, relocated_source

TRAIN = ["-a", "baseline", "-l", "mse", "-P", "personalized"]


def tree_hash(root: Path) -> dict[str, str]:
    """Every file under ``root`` (lock files included) -> its SHA-256, and every folder -> 'dir'."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        out[rel] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


@pytest.fixture(scope="module")
def original(tmp_path_factory) -> Path:
    """A project whose stores are under runs/ (relative paths, as in a real project)."""
    root = tmp_path_factory.mktemp("reloc") / "orig"
    root.mkdir()
    write_tiny_dataset(root / "tiny", patients=2, lobes=("ur",), trajectories=3, frames=6, image_size=32)
    write_config(root, steps=2, val_every=2)
    return root


def _train(cli, root: Path, *extra: str) -> tuple[int, str, str]:
    return cli("train", "-c", str(root / "experiments.yaml"), *TRAIN, "-q", *extra)


def _runs(root: Path, *overrides: str):
    cfg = load_config(root / "experiments.yaml", overrides=overrides)
    client = client_for(cfg)
    return cfg, search_runs(client, [experiment_id(client, cfg)])


def test_a_copied_project_writes_and_reads_only_its_own_store(cli, original, tmp_path):
    code, out, err = _train(cli, original)
    assert code == 0, out + err
    copy = tmp_path / "copy"
    subprocess.run(["cp", "-a", str(original), str(copy)], check=True)
    before = tree_hash(original)

    code, out, err = _train(cli, copy, "--seed", "1")  # a new run in the copy
    assert code == 0, out + err
    cfg, runs = _runs(copy)
    assert len(runs) == 2
    for run in runs:  # old and new runs: artifacts in the copy, and present there
        where = _local_path(run.info.artifact_uri)
        assert where is not None and where.is_relative_to(copy / "runs" / "artifacts"), run.info.artifact_uri
        assert any(where.rglob("*")), f"no artifacts under {where}"
        # dataset inputs resolve like artifacts: the copy's own dataset, for the old run and the new one
        sources = {json.loads(d.dataset.source)["uri"] for d in run.inputs.dataset_inputs}
        assert sources == {(copy / "tiny").as_uri()}, sources
    assert tree_hash(original) == before  # the original's tree is byte-identical


def test_dataset_sources_move_only_with_the_project(tmp_path):
    old, new = tmp_path / "a" / "orig", tmp_path / "b" / "copy"
    assert moved_roots(old / "runs" / "artifacts", new / "runs" / "artifacts") == (old, new)
    (new / "data" / "tiny").mkdir(parents=True)
    source = json.dumps({"uri": (old / "data" / "tiny").as_uri()})
    assert json.loads(relocated_source(source, old, new))["uri"] == (new / "data" / "tiny").as_uri()
    outside = json.dumps({"uri": (tmp_path / "shared" / "tiny").as_uri()})
    assert relocated_source(outside, old, new) is None  # a dataset outside the project stays where it is
    not_copied = json.dumps({"uri": (old / "data" / "other").as_uri()})
    assert relocated_source(not_copied, old, new) is None  # not in the copy: the old path is the only one
    assert relocated_source("not json", old, new) is None


def test_a_changed_artifact_root_is_refused_in_one_line_until_the_folder_moves(cli, original, tmp_path):
    project = tmp_path / "p"
    subprocess.run(["cp", "-a", str(original), str(project)], check=True)
    code, out, err = _train(cli, project)  # (the copy is relocated here)
    assert code == 0, out + err
    elsewhere = tmp_path / "elsewhere"
    code, out, err = _train(cli, project, "--set", f"runs.artifacts={elsewhere}")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and "Traceback" not in out + err, out + err
    assert str(project / "runs" / "artifacts") in lines[0] and str(elsewhere) in lines[0]
    assert not elsewhere.exists()

    (project / "runs" / "artifacts").rename(elsewhere)  # the fix the line suggests: move the folder
    code, out, err = _train(cli, project, "--seed", "2", "--set", f"runs.artifacts={elsewhere}")
    assert code == 0, out + err
    _, runs = _runs(project, f"runs.artifacts={elsewhere}")
    assert runs and all(_local_path(r.info.artifact_uri).is_relative_to(elsewhere) for r in runs)
