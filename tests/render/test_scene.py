"""Rendering inside a hand-made bent tube: lumen appearance, pose dependence, buffers, realism options."""

from __future__ import annotations

import numpy as np
import pytest
from generator_refs import tube_surface

from bronchocli.config import Realism
from bronchocli.render.appearance import (
    mucosa_colours,
    prepare_surface,
    split_blocks,
    triangles,
)
from bronchocli.render.scene import FrameRenderer, blur


def _rot_down() -> np.ndarray:
    """Camera looking down -z (the straight part of the tube), up = +x, left = up x forward."""
    f, u = np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0])
    return np.column_stack([f, np.cross(u, f), u])


@pytest.fixture(scope="module")
def surface():
    return prepare_surface(tube_surface(), texture=False)


@pytest.fixture(scope="module")
def renderer(surface):
    with FrameRenderer(surface, width=64, realism=Realism(texture=False)) as r:
        yield r


def test_lumen_is_lit_and_darker_in_the_middle(renderer):
    frame = renderer.render(np.array([0.0, 0.0, -10.0]), _rot_down(), radius_mm=8.0)
    assert frame.shape == (64, 64, 3) and frame.dtype == np.uint8
    grey = frame.astype(float).mean(2)
    centre = grey[28:36, 28:36].mean()
    ring = np.concatenate([grey[4:12, 28:36].ravel(), grey[52:60, 28:36].ravel(),
                           grey[28:36, 4:12].ravel(), grey[28:36, 52:60].ravel()]).mean()
    assert ring > 20, "the wall near the camera should be lit"
    assert centre < 0.5 * ring, "the far lumen should be darker than the nearby wall"
    # The airway colour: red dominates green dominates blue on the wall.
    r, g, b = frame[4:12, 28:36].reshape(-1, 3).mean(0)
    assert r > g > b


def test_frames_are_copies_and_vary_with_pose(renderer):
    a = renderer.render(np.array([0.0, 0.0, -10.0]), _rot_down(), radius_mm=8.0)
    b = renderer.render(np.array([3.0, 1.0, -25.0]), _rot_down(), radius_mm=8.0)
    a_again = renderer.render(np.array([0.0, 0.0, -10.0]), _rot_down(), radius_mm=8.0)
    assert np.abs(a.astype(int) - b).mean() > 3, "a different pose must give a different frame"
    np.testing.assert_array_equal(a, a_again)  # deterministic, and `a` was not overwritten by later renders


def test_off_centre_camera_sees_the_near_wall_brighter(renderer):
    """Camera 4 mm towards +x (image up): the wall above is nearer, so brighter than the wall below."""
    frame = renderer.render(np.array([4.0, 0.0, -10.0]), _rot_down(), radius_mm=8.0).astype(float).mean(2)
    assert frame[:12, 20:44].mean() > frame[-12:, 20:44].mean() + 20
    # Lines parallel to the view axis vanish at the principal point: the dark far lumen stays centred.
    dark_row = np.argmin(frame[:, 24:40].mean(1))
    assert 24 <= dark_row <= 40


def test_automatic_gain_brightens_wide_airways(surface):
    pos, R = np.array([0.0, 0.0, -10.0]), _rot_down()
    with FrameRenderer(surface, width=48, realism=Realism(texture=False)) as r:
        narrow = r.render(pos, R, radius_mm=2.0).mean()
        wide = r.render(pos, R, radius_mm=8.0).mean()
    assert wide > narrow + 5


def test_blocks_render_the_same_image(surface):
    pos, R = np.array([1.0, -1.0, -20.0]), _rot_down()
    blocks = split_blocks(surface, 8)
    assert len(blocks) == 8
    assert sum(b.GetNumberOfPolys() for b in blocks) == surface.GetNumberOfPolys()
    with FrameRenderer(surface, width=48, blocks=1) as one, FrameRenderer(surface, width=48, blocks=8) as many:
        a, b = one.render(pos, R, 8.0), many.render(pos, R, 8.0)
    assert np.abs(a.astype(int) - b).mean() < 0.5


def test_realism_options_change_the_frame(surface):
    pos, R = np.array([2.0, 0.0, -15.0]), _rot_down()

    def shot(realism, surf=surface):
        with FrameRenderer(surf, width=48, realism=realism) as r:
            return r.render(pos, R, 8.0).astype(float)

    plain = shot(Realism(texture=False, specular=0.0, vignetting=False, blur=0.0))
    vignette = shot(Realism(texture=False, specular=0.0, vignetting=True, blur=0.0))
    corners = (slice(0, 6), slice(0, 6))
    assert vignette[corners].mean() < plain[corners].mean() - 5, "vignetting darkens the corners"
    # Specular shows where the wall faces the light: look sideways at the wall, low gain (no saturation).
    side = np.column_stack([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    with FrameRenderer(surface, width=48, realism=Realism(texture=False, specular=0.0, vignetting=False)) as r:
        matte = r.render(np.array([0.0, 0.0, -20.0]), side, 2.0).astype(float)
    with FrameRenderer(surface, width=48, realism=Realism(texture=False, specular=1.0, vignetting=False)) as r:
        shiny = r.render(np.array([0.0, 0.0, -20.0]), side, 2.0).astype(float)
    assert matte[20:28, 20:28, 1].mean() < 200
    assert shiny[20:28, 20:28, 1].mean() > matte[20:28, 20:28, 1].mean() + 20, "specular highlight facing the wall"
    assert abs(shiny[:4, :4].mean() - matte[:4, :4].mean()) < 3, "no highlight at grazing angles"
    blurred = shot(Realism(texture=False, specular=0.0, vignetting=False, blur=2.0))
    assert np.abs(np.diff(blurred, axis=1)).mean() < np.abs(np.diff(plain, axis=1)).mean()
    textured_surface = prepare_surface(tube_surface(), texture=True, seed=3)
    textured = shot(Realism(texture=True, specular=0.0, vignetting=False), textured_surface)
    assert np.abs(textured - plain).mean() > 2


def test_mucosa_colours_are_seeded_and_airway_coloured():
    pts = np.random.default_rng(0).uniform(-20, 20, (500, 3))
    a, b, c = mucosa_colours(pts, 1), mucosa_colours(pts, 1), mucosa_colours(pts, 2)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - c).mean() > 3
    mean = a.astype(float).mean(0)
    assert mean[0] > mean[1] > mean[2]


def test_prepared_surface_is_triangles_with_normals():
    poly = prepare_surface(tube_surface(), texture=True, seed=0)
    pts, tris = triangles(poly)
    assert tris.shape[1] == 3 and len(pts) == poly.GetNumberOfPoints()
    assert poly.GetPointData().GetNormals() is not None
    assert poly.GetPointData().GetScalars().GetNumberOfComponents() == 3


def test_blur_is_identity_at_zero_and_smooths_otherwise():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (16, 16, 3), dtype=np.uint8)
    assert blur(img, 0.0) is img
    out = blur(img, 1.5)
    assert out.dtype == np.uint8 and out.std() < img.std()
