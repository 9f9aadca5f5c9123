"""The real CT-derived tree of tests/fixtures/airways: four lobe paths, and a small dataset that renders right."""

from __future__ import annotations

import json

import numpy as np
from generator_refs import check_ground_truth, read_csv_rows
from PIL import Image

from bronchocli.config import Config


def test_real_tree_renders_along_four_lobe_paths(real_tree, tmp_path):
    from bronchocli.anatomy import load_anatomy
    from bronchocli.generation.pipeline import generate_dataset

    tree = load_anatomy(real_tree, voxel_mm=1.0, lobe_generation=Config(name="x").dataset.generate.lobe_generation)
    assert set(tree.lobe_paths) == {"ur", "br", "ul", "bl"}
    assert all(p.arc_length[-1] > 80 for p in tree.lobe_paths.values())
    cfg = Config(name="real").with_values({
        "dataset.generate.anatomy": str(real_tree), "dataset.generate.voxel_mm": 1.0,
        "dataset.generate.trajectories": 1, "dataset.generate.max_frames": 4, "dataset.generate.image_size": 48,
    })
    root = generate_dataset(cfg, root=tmp_path / "real", workers=1, progress=False)
    meta = json.loads((root / "dataset.json").read_text())
    patient = "TestSubject002MajorAirways"
    assert meta["patients"] == [patient] and meta["counts"]["frames"] == 16
    # Positions map back onto the source anatomy's own mm coordinates.
    assert meta["voxel_grid"][patient]["origin_mm"] == [float(v) for v in tree.origin_mm]
    assert check_ground_truth(root, patient, tree) == 16
    frames = np.stack([np.asarray(Image.open(root / r["filename"])) for r in read_csv_rows(root, patient)])
    assert frames.shape == (16, 48, 48, 3)
    grey = frames.astype(float).mean(3)
    assert grey.mean() > 25 and (grey.reshape(16, -1).std(1) > 5).all()
