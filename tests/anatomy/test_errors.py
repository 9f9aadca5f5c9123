"""Bad anatomy input: one clear, one-line DataError naming the file (or ConfigError for bad settings)."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_airway import synthetic_tree, tree_graph, write_graph, write_volume

from bronchocli.anatomy import load_anatomy
from bronchocli.errors import ConfigError, DataError


def raises(exc, *parts: str):
    """Context manager: ``exc`` whose one-line message contains every part."""
    class _Check:
        def __enter__(self):
            self.ctx = pytest.raises(exc)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *a):
            handled = self.ctx.__exit__(*a)
            msg = str(self.info.value)
            assert "\n" not in msg, msg
            for part in parts:
                assert part in msg, (part, msg)
            return handled
    return _Check()


def test_missing_file(tmp_path):
    path = tmp_path / "nope.vtu"
    with raises(DataError, str(path), "not found"):
        load_anatomy(path)


def test_unknown_extension(tmp_path):
    path = tmp_path / "airway.ply"
    path.write_text("ply")
    with raises(DataError, str(path), ".ply", ".vtu", ".nii.gz", ".stl", "procedural"):
        load_anatomy(path)


@pytest.mark.parametrize("ext", [".vtu", ".vtp"])
def test_graph_without_radii(tmp_path, ext):
    points, _, edges = tree_graph(synthetic_tree())
    path = write_graph(tmp_path / f"g{ext}", points, edges, {"horsfield_order": np.ones(len(points))})
    with raises(DataError, str(path), "radius", "horsfield_order"):
        load_anatomy(path)


def test_disconnected_graph(tmp_path):
    points, radii, edges = tree_graph(synthetic_tree())
    far = points + 500.0
    path = write_graph(tmp_path / "two.vtp", np.concatenate([points, far]),
                       np.concatenate([edges, edges + len(points)]), {"radius": np.concatenate([radii, radii])})
    with raises(DataError, str(path), "disconnected", "2 pieces"):
        load_anatomy(path)


@pytest.mark.parametrize("ext", [".nii.gz", ".mhd", ".nrrd"])
def test_volume_without_foreground(tmp_path, ext):
    path = write_volume(tmp_path / f"empty{ext}", np.zeros((20, 16, 12), dtype=np.uint8), np.zeros(3), 1.0)
    with raises(DataError, str(path), "no foreground"):
        load_anatomy(path)


@pytest.mark.parametrize("name", ["junk.vtu", "junk.vtp", "junk.nii.gz", "junk.mhd", "junk.nrrd", "junk.stl", "junk.obj"])
def test_unreadable_files(tmp_path, capfd, name):
    path = tmp_path / name
    path.write_bytes(b"not really a file of this type")
    with raises(DataError, str(path)):
        load_anatomy(path)
    out, err = capfd.readouterr()
    assert "ERR" not in out + err  # VTK's own error log is captured into the one-line message


def test_truncated_or_incomplete_volumes(tmp_path):
    mask = np.ones((12, 12, 12), dtype=np.uint8)
    nrrd = write_volume(tmp_path / "cut.nrrd", mask, np.zeros(3), 1.0)
    nrrd.write_bytes(nrrd.read_bytes()[:-100])
    with raises(DataError, "cut.nrrd", "truncated"):
        load_anatomy(nrrd)
    mhd = write_volume(tmp_path / "lost.mhd", mask, np.zeros(3), 1.0)
    for data in tmp_path.glob("lost.*raw"):
        data.unlink()
    with raises(DataError, "lost.mhd", "missing"):
        load_anatomy(mhd)


def test_graph_that_never_branches(tmp_path):
    pts = np.stack([np.zeros(10), np.zeros(10), np.linspace(0, -50, 10)], axis=1)
    path = write_graph(tmp_path / "tube.vtp", pts, np.stack([np.arange(9), np.arange(1, 10)], 1),
                       {"radius": np.full(10, 5.0)})
    with raises(DataError, "tube.vtp", "does not bifurcate"):
        load_anatomy(path)


def test_bad_settings(tmp_path):
    with raises(ConfigError, "voxel_mm", "-1"):
        load_anatomy("procedural", voxel_mm=-1)
    with raises(ConfigError, "generation", "1"):
        load_anatomy("procedural", lobe_generation=1)


def test_centreline_must_be_a_graph_in_the_same_frame(tmp_path):
    from synthetic_airway import write_mesh

    from bronchocli.anatomy import lumen_surface

    mesh = write_mesh(tmp_path / "a.stl", lumen_surface(synthetic_tree(), 1.0))
    with raises(DataError, "cl.stl", ".vtu or .vtp"):
        load_anatomy(mesh, centreline=tmp_path / "cl.stl")
    points, radii, edges = tree_graph(synthetic_tree())
    shifted = write_graph(tmp_path / "far.vtp", points + 1000.0, edges, {"radius": radii})
    with raises(DataError, "far.vtp", "outside", "same coordinates"):
        load_anatomy(mesh, centreline=shifted)
