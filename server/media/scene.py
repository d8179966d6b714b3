"""What a rendered picture depends on besides the clip: settings and camera.  Pure numpy, cheap to import."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
RENDERER_VERSION = 2  # bump when the picture or its encoding changes for the same inputs: part of every cache key


@dataclass(frozen=True)
class RenderSettings:
    """Everything besides the clip that decides the pixels."""

    width: int = 640
    height: int = 480
    shadows: bool = True
    yfov_deg: float = 30.0
    azimuth_deg: float = 55.0  # camera direction around the character, from its front (+Z) towards its left (+X)
    elevation_deg: float = 8.0
    margin: float = 0.12  # share of the frame kept free around the motion
    background: tuple[float, float, float] = (0.87, 0.89, 0.92)
    body_color: tuple[float, float, float] = (0.72, 0.70, 0.67)
    grid_spacing_m: float = 0.25  # ground grid (adjusted per clip so a travelling loop scrolls seamlessly)

    def as_dict(self) -> dict:
        return {**asdict(self), "renderer_version": RENDERER_VERSION}


@dataclass(frozen=True)
class Framing:
    """A fixed camera: ``eye`` and ``target`` in world metres (Y up)."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]

    def pose(self) -> Array:
        """4x4 camera-to-world matrix (pyrender cameras look along their -Z)."""
        eye, target = np.array(self.eye), np.array(self.target)
        back = eye - target
        back /= np.linalg.norm(back)
        right = np.cross([0.0, 1.0, 0.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
        return m


def frame_motion(points: Array, settings: RenderSettings, padding: float = 0.12) -> Framing:
    """The camera that keeps every point of ``points (..., 3)`` (metres), grown by ``padding`` metres, inside the
    frame with the settings' margin.

    Callers pass the joint positions of every clip shown under this camera (the body extends ~0.1 m beyond them).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    target = 0.5 * (p.min(axis=0) + p.max(axis=0))
    az, el = np.radians(settings.azimuth_deg), np.radians(settings.elevation_deg)
    back = np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    rel = p - target
    ty = np.tan(np.radians(settings.yfov_deg) / 2) * (1 - 2 * settings.margin)
    tx = ty * settings.width / settings.height
    # Each point needs the camera at least this far back to fit horizontally and vertically.
    along = rel @ back + padding
    need = np.maximum((np.abs(rel @ right) + padding) / tx, (np.abs(rel @ up) + padding) / ty) + along
    # Re-centre vertically on what the camera sees, so the margin above the head and below the feet match.
    dist = float(need.max())
    return Framing(tuple(target + back * dist), tuple(target))
