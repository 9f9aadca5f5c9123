"""Camera intrinsics against hand-computed values and against what VTK actually renders."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bronchocli.render.camera import intrinsics, pixel_rays, project


def test_intrinsics_hand_computed():
    cam = intrinsics(64, 64, 70.0)
    assert cam.fx == pytest.approx(32 / math.tan(math.radians(35)))
    assert cam.fx == pytest.approx(45.7007, abs=1e-4)
    assert (cam.cx, cam.cy) == (31.5, 31.5)
    wide = intrinsics(100, 50, 90.0)
    assert wide.fy == pytest.approx(25.0) and wide.fx == pytest.approx(25.0)
    assert (wide.cx, wide.cy) == (49.5, 24.5)


def test_project_and_rays_are_inverse():
    cam = intrinsics(128, 128, 70.0)
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(1, 10, 50), rng.uniform(-3, 3, 50), rng.uniform(-3, 3, 50)])
    rays = pixel_rays(project(p, cam), cam)
    np.testing.assert_allclose(rays, p / np.linalg.norm(p, axis=1, keepdims=True), atol=1e-12)
    # A point left of the axis (y > 0) is in the left half, one above (z > 0) in the top half.
    u, v = project(np.array([[5.0, 1.0, 1.0]]), cam)[0]
    assert u < cam.cx and v < cam.cy


def _sphere(centre, radius=1.0):
    import vtk

    s = vtk.vtkSphereSource()
    s.SetCenter(*centre)
    s.SetRadius(radius)
    s.SetThetaResolution(48)
    s.SetPhiResolution(48)
    s.Update()
    return s.GetOutput()


@pytest.mark.parametrize("offset", [(20.0, 5.0, -3.0), (15.0, -4.0, 6.0), (25.0, 0.0, 0.0)])
def test_rendered_blob_lands_where_the_intrinsics_say(offset):
    """A small sphere at a known camera-frame direction appears at project(direction): orientation, flip, fx."""
    from bronchocli.config import Realism
    from bronchocli.render.appearance import prepare_surface
    from bronchocli.render.scene import FrameRenderer

    R = Rotation.from_euler("XYZ", [30, -20, 75], degrees=True).as_matrix()
    cam_pos = np.array([3.0, -7.0, 11.0])
    centre = cam_pos + R @ np.asarray(offset)
    surface = prepare_surface(_sphere(centre), texture=False)
    with FrameRenderer(surface, width=96, fov_deg=70.0, realism=Realism(vignetting=False, specular=0.0)) as r:
        frame = r.render(cam_pos, R, radius_mm=20.0)
        cam = r.camera_model
    mask = frame.max(axis=2) > 10
    assert 10 < mask.sum() < 600
    v, u = np.nonzero(mask)
    expected = project(np.asarray(offset)[None], cam)[0]
    assert abs(u.mean() - expected[0]) < 0.3  # a half-pixel convention error fails
    assert abs(v.mean() - expected[1]) < 0.3
