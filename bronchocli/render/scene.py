"""The VTK scene that renders one bronchoscopy frame per camera pose (offscreen, EGL).

One lumen surface (optionally in spatial blocks), a perspective camera inside
it, and a single positional spot light at the camera tip (the bronchoscope's
light guide). Its distance attenuation ``1 / (c + (q / r^2) d^2)`` is scaled by
the local airway radius ``r`` at the camera: no fixed attenuation looks right
from the trachea (r ~ 8 mm) to r ~ 1 mm, and this acts like the automatic gain
of a real bronchoscope. Multisampling is off (it halves the frame
rate of the software renderer); pixels are copied out of VTK's buffer on every
frame (VTK reuses one buffer).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from ..config import Realism
from . import configure_environment
from .appearance import AIRWAY_RGB, split_blocks
from .camera import FAR_MM, NEAR_MM, Intrinsics, intrinsics

configure_environment()

import vtkmodules.vtkRenderingOpenGL2  # noqa: E402,F401  (registers the OpenGL/EGL implementations)
from vtkmodules.util.numpy_support import vtk_to_numpy  # noqa: E402
from vtkmodules.vtkCommonCore import vtkUnsignedCharArray  # noqa: E402
from vtkmodules.vtkCommonDataModel import vtkPolyData  # noqa: E402
from vtkmodules.vtkRenderingCore import (  # noqa: E402
    vtkActor,
    vtkLight,
    vtkPolyDataMapper,
    vtkRenderer,
    vtkRenderWindow,
)

LIGHT_CONSTANT = 0.35  # attenuation constant term
LIGHT_QUADRATIC = 0.12  # quadratic term per (mm / local radius)^2
MIN_GAIN_RADIUS_MM = 0.5  # below this radius the gain stops growing (no blow-up at tiny radii)
SPOT_CONE_DEG = 60.0  # spot cone of the headlight with vignetting ...
SPOT_EXPONENT = 3.0  # ... and its fall-off towards the image border
SPECULAR_POWER = 20.0
TRIANGLES_PER_BLOCK = 2000  # spatial blocks of about this size let VTK cull what is off-screen;
# measured on a 164k-triangle tree at 128 px: 1 block 31 fps, 8 blocks 39, 64-128 blocks 80-88, 256+ slower


def blur(frame: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of an ``H x W x 3`` uint8 frame by ``sigma`` pixels (0: unchanged)."""
    if sigma <= 0:
        return frame

    out = gaussian_filter(frame.astype(np.float32), sigma=(sigma, sigma, 0), mode="nearest")
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


class FrameRenderer:
    """Offscreen renderer of one lumen surface: ``render(position_mm, R, radius_mm) -> H x W x 3 uint8``.

    ``R``'s columns are the camera's (forward, left, up) in the surface's mm
    frame (docs/conventions.md), so VTK's direction of projection is ``R[:, 0]`` and its
    view-up ``R[:, 2]``. Row 0 of the returned frame is the top of the image.
    """

    def __init__(self, surface: vtkPolyData, *, width: int, height: int | None = None,
                 fov_deg: float = 70.0, realism: Realism | None = None, blocks: int | None = None) -> None:
        self.realism = realism or Realism()
        self.camera_model: Intrinsics = intrinsics(width, height, fov_deg)
        self.width, self.height = self.camera_model.width, self.camera_model.height
        self._window = vtkRenderWindow()
        self._window.SetOffScreenRendering(1)
        self._window.SetMultiSamples(0)
        self._window.SetSize(self.width, self.height)
        self._renderer = vtkRenderer()
        self._renderer.SetBackground(0.0, 0.0, 0.0)
        self._renderer.AutomaticLightCreationOff()
        self._renderer.TwoSidedLightingOn()
        self._window.AddRenderer(self._renderer)
        self._mappers = []  # keep references: VTK objects die with their last Python reference
        if blocks is None:
            blocks = max(1, surface.GetNumberOfPolys() // TRIANGLES_PER_BLOCK)
        for block in split_blocks(surface, blocks):
            self._renderer.AddActor(self._actor(block))
        self._light = self._headlight()
        self._renderer.AddLight(self._light)
        self._camera = self._renderer.GetActiveCamera()
        self._camera.SetViewAngle(fov_deg)
        self._pixels = vtkUnsignedCharArray()

    def _actor(self, block: vtkPolyData) -> vtkActor:
        mapper = vtkPolyDataMapper()
        mapper.SetInputData(block)
        textured = block.GetPointData().GetScalars() is not None
        mapper.SetScalarVisibility(textured)
        if textured:
            mapper.SetColorModeToDirectScalars()
        mapper.StaticOn()  # the mesh never changes: skip pipeline checks per frame
        self._mappers.append(mapper)
        actor = vtkActor()
        actor.SetMapper(mapper)
        prop = actor.GetProperty()
        prop.SetColor(*AIRWAY_RGB)
        prop.SetAmbient(0.0)
        prop.SetDiffuse(1.0)
        prop.SetSpecular(self.realism.specular)
        prop.SetSpecularPower(SPECULAR_POWER)
        prop.SetSpecularColor(1.0, 1.0, 1.0)
        prop.SetInterpolationToGouraud()
        return actor

    def _headlight(self) -> vtkLight:
        light = vtkLight()
        light.SetLightTypeToSceneLight()  # placed explicitly at the camera tip every frame
        light.SetPositional(True)
        light.SetColor(1.0, 1.0, 1.0)
        light.SetIntensity(1.0)
        if self.realism.vignetting:
            light.SetConeAngle(SPOT_CONE_DEG)
            light.SetExponent(SPOT_EXPONENT)
        else:
            light.SetConeAngle(90.0)  # >= 90: a point light, no spot fall-off
            light.SetExponent(0.0)
        return light

    def place(self, position_mm: np.ndarray, rotation: np.ndarray, radius_mm: float) -> None:
        """Put the camera and its light at ``position_mm`` with orientation ``rotation``."""
        p = np.asarray(position_mm, dtype=np.float64)
        R = np.asarray(rotation, dtype=np.float64)
        focal = p + 10.0 * R[:, 0]
        self._camera.SetPosition(*p)
        self._camera.SetFocalPoint(*focal)
        self._camera.SetViewUp(*R[:, 2])
        self._camera.SetClippingRange(NEAR_MM, FAR_MM)
        self._light.SetPosition(*p)
        self._light.SetFocalPoint(*focal)
        r = max(float(radius_mm), MIN_GAIN_RADIUS_MM)
        self._light.SetAttenuationValues(LIGHT_CONSTANT, 0.0, LIGHT_QUADRATIC / (r * r))

    def render(self, position_mm: np.ndarray, rotation: np.ndarray, radius_mm: float) -> np.ndarray:
        """The frame seen from ``position_mm`` (mm) with camera axes ``rotation`` (3x3), as H x W x 3 uint8."""
        self.place(position_mm, rotation, radius_mm)
        self._window.Render()
        w, h = self.width, self.height
        self._window.GetPixelData(0, 0, w - 1, h - 1, 0, self._pixels, 0)
        # VTK stores rows bottom-up in one reused buffer: flip and copy.
        frame = vtk_to_numpy(self._pixels).reshape(h, w, 3)[::-1].copy()
        return blur(frame, self.realism.blur)

    def close(self) -> None:
        """Release the OpenGL context (the renderer cannot be used afterwards)."""
        if self._window is not None:
            self._window.Finalize()
            self._window = None

    def __enter__(self) -> "FrameRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
