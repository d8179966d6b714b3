"""Offscreen rendering of the skinned character with pyrender on OSMesa (CPU only).

pyrender does not skin, so every frame is skinned on the CPU with ``anim_core`` and written into the mesh's vertex
buffer in place.  Three defects of pyrender 0.1.45 with a current PyOpenGL/NumPy are worked around here, once, on
import: NumPy 2 has no ``np.infty``; PyOpenGL >= 3.1.4 returns a fresh ctypes pointer from
``contextdata.getContext()`` on every call, so pyrender's shader cache (keyed by it) misses on every frame and
leaks a compiled program per frame (~4 MB); and the OSMesa platform must be chosen before OpenGL is imported.
"""

from __future__ import annotations

import ctypes
import os
import shutil
import tempfile
from collections.abc import Iterator
from functools import cache
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
from numpy.typing import NDArray

if not hasattr(np, "infty"):
    np.infty = np.inf  # type: ignore[attr-defined]  # noqa: NPY201 (removed in NumPy 2, pyrender uses it)

import OpenGL

# glGetError after every call costs ~10 ms a frame in pyrender's many small calls; errors still surface as
# broken pictures, which the tests look at.
OpenGL.ERROR_CHECKING = False
import OpenGL.contextdata  # noqa: E402

_get_context = OpenGL.contextdata.getContext


def _stable_context(context: object = None) -> object:
    """The current context as a plain integer, so it can key caches (the ctypes pointer is new every call)."""
    ctx = _get_context(context)
    if isinstance(ctx, int):
        return ctx
    return ctypes.cast(ctx, ctypes.c_void_p).value


OpenGL.contextdata.getContext = _stable_context

import pyrender  # noqa: E402
from OpenGL import GL  # noqa: E402
from pyrender.shader_program import ShaderProgramCache  # noqa: E402

from anim_core.math.skinning import SkinnedMesh  # noqa: E402

from .scene import Framing, RenderSettings  # noqa: E402

Array = NDArray[np.float64]
SHADOW_MAP_SIZE = 1024
SHADOW_RADIUS_M = 1.6  # half-size of the square the key light's shadow map covers, around the character
pyrender.renderer.SHADOW_TEX_SZ = SHADOW_MAP_SIZE  # the shadow pass's viewport; pyrender reads this global


# pyrender's mesh.frag is physically based (GGX, Fresnel, sRGB pow() per texel and per pixel) and filters shadows
# with 36 taps; on llvmpipe that costs more than everything else in a frame.  These replacements keep every uniform
# pyrender sets but shade with Lambert + a Blinn highlight, gamma 2, and one bilinear shadow tap (the shadow map is
# fitted to the character: 3 mm texels), outside of which there is no shadow.
_CHEAP_FUNCTIONS = {
    "vec3 compute_brdf(": """vec3 compute_brdf(vec3 n, vec3 v, vec3 l,
                  float roughness, float metalness,
                  vec3 f0, vec3 c_diff, vec3 albedo,
                  vec3 radiance)
{
    float nl = clamp(dot(n, l), 0.0, 1.0);
    float nh = clamp(dot(n, normalize(l + v)), 0.0, 1.0);
    float s = nh * nh; s = s * s; s = s * s; s = s * s;
    return radiance * nl * (c_diff / PI + f0 * s * (1.0 - roughness));
}
""",
    "float PCF(": """float PCF(sampler2D depths, vec2 size, vec2 uv, float compare){
    if (any(lessThan(uv, vec2(0.0))) || any(greaterThan(uv, vec2(1.0)))) return 0.0;
    return texture2DShadowLerp(depths, size, uv, compare);
}
""",
    "vec4 srgb_to_linear(": """vec4 srgb_to_linear(vec4 srgb)
{
    return vec4(srgb.xyz * srgb.xyz, srgb.w);
}
""",
}


def _replace_function(source: str, signature: str, replacement: str) -> str:
    start = source.index(signature)
    end = source.index("\n}\n", start) + 3
    return source[:start] + replacement + source[end:]


@cache
def _shader_dir() -> str:
    """A copy of pyrender's shaders (made at run time, never committed) with the cheap functions above."""
    src = Path(pyrender.__file__).parent / "shaders"
    dst = Path(tempfile.mkdtemp(prefix="animstudy-shaders-"))
    shutil.copytree(src, dst, dirs_exist_ok=True)
    frag = dst / "mesh.frag"
    text = frag.read_text()
    for signature, replacement in _CHEAP_FUNCTIONS.items():
        text = _replace_function(text, signature, replacement)
    text = text.replace("pow(color.xyz, vec3(1.0/2.2))", "sqrt(color.xyz)")
    frag.write_text(text)
    return str(dst)


def _grid_texture(size: int = 256, line: int = 3) -> NDArray[np.uint8]:
    """One grid cell: light floor with a subtle darker line along two edges (tiles into a grid)."""
    img = np.full((size, size, 3), 214, dtype=np.uint8)
    img[:line, :] = 178
    img[:, :line] = 178
    return img


class ClipRenderer:
    """Renders frames of one character (a fixed mesh topology) under one camera.

    Not thread-safe; one per process (OSMesa contexts are per thread).
    """

    def __init__(self, mesh: SkinnedMesh, faces: NDArray[np.intp], framing: Framing, settings: RenderSettings,
                 bounds: Array, grid_spacing_m: float | None = None, floor_size: float = 30.0) -> None:
        self.mesh = mesh
        self.settings = settings
        s = settings
        self.scene = pyrender.Scene(bg_color=[*s.background, 1.0], ambient_light=[0.45, 0.46, 0.50])
        body = pyrender.MetallicRoughnessMaterial(baseColorFactor=[*s.body_color, 1.0], metallicFactor=0.0,
                                                  roughnessFactor=0.75)
        v, n = mesh.vertices.astype(np.float32), mesh.normals.astype(np.float32)
        self._primitive = pyrender.Primitive(positions=v, normals=n, indices=faces, material=body)
        # Shadow and culling bounds must hold every frame, not just the bind pose.
        self._primitive._bounds = np.asarray(bounds, dtype=np.float64)
        self.body = self.scene.add(pyrender.Mesh([self._primitive]))

        cells = floor_size / (grid_spacing_m or s.grid_spacing_m)
        half = floor_size / 2
        floor = pyrender.Primitive(
            positions=np.array([[-half, 0, -half], [half, 0, -half], [half, 0, half], [-half, 0, half]], np.float32),
            normals=np.tile(np.array([[0.0, 1.0, 0.0]], np.float32), (4, 1)),
            texcoord_0=np.array([[0, 0], [cells, 0], [cells, cells], [0, cells]], np.float32),
            indices=np.array([[0, 2, 1], [0, 3, 2]]),
            material=pyrender.MetallicRoughnessMaterial(
                baseColorTexture=pyrender.Texture(source=_grid_texture(), source_channels="RGB"),
                metallicFactor=0.0, roughnessFactor=1.0))
        self._floor = self.scene.add(pyrender.Mesh([floor]))
        self.scene.add(pyrender.PerspectiveCamera(yfov=np.radians(s.yfov_deg), aspectRatio=s.width / s.height),
                       pose=framing.pose())
        key_pose = np.eye(4)
        key_pose[:3, :3] = Framing((2.0, 4.0, 3.0), (0.0, 0.0, 0.0)).pose()[:3, :3]  # from above, front-left
        key = pyrender.DirectionalLight(color=[1.0, 0.98, 0.95], intensity=3.2)
        # A small shadow map fitted to the character, clamped so the floor beyond it is lit, not tiled.
        key.shadow_texture = pyrender.Texture(
            width=SHADOW_MAP_SIZE, height=SHADOW_MAP_SIZE, source_channels="D", data_format=GL.GL_FLOAT,
            sampler=pyrender.Sampler(wrapS=pyrender.GLTF.CLAMP_TO_EDGE, wrapT=pyrender.GLTF.CLAMP_TO_EDGE))
        key._get_shadow_camera = lambda scale: pyrender.OrthographicCamera(
            xmag=SHADOW_RADIUS_M, ymag=SHADOW_RADIUS_M, znear=0.01 * scale, zfar=10 * scale)
        self.scene.add(key, pose=key_pose)
        self._renderer = pyrender.OffscreenRenderer(s.width, s.height)
        self._renderer._renderer._program_cache = ShaderProgramCache(shader_dir=_shader_dir())
        # OSMesa has no framebuffer objects, so pyrender reads back depth after every frame; nothing here uses it.
        self._renderer._renderer.read_depth_buf = lambda: None
        # The floor receives shadows but casts none: leave it out of the shadow pass (a million depth fragments).
        shadow_pass = self._renderer._renderer._shadow_mapping_pass
        floor_mesh = self._floor.mesh

        def character_shadow_pass(*args: object) -> None:
            if not self.body.mesh.is_visible:  # pyrender fails on a shadow pass that draws nothing
                shadow_pass(*args)
                return
            floor_mesh.is_visible = False
            try:
                shadow_pass(*args)
            finally:
                floor_mesh.is_visible = True

        self._renderer._renderer._shadow_mapping_pass = character_shadow_pass
        self._flags = pyrender.RenderFlags.SHADOWS_DIRECTIONAL if s.shadows else pyrender.RenderFlags.NONE
        self._uploaded = False

    def _upload(self, positions: Array, normals: Array) -> None:
        data = np.ascontiguousarray(np.hstack([positions, normals]), dtype=np.float32)
        if not self._uploaded:  # the first render creates the buffers; later frames overwrite them in place
            bounds = self._primitive._bounds
            self._primitive.positions, self._primitive.normals = data[:, :3], data[:, 3:]
            self._primitive._bounds = bounds
            return
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self._primitive._buffers[0])
        GL.glBufferSubData(GL.GL_ARRAY_BUFFER, 0, data.nbytes, data)

    def render(self, world_rotations: Array, world_positions: Array, floor_shift: Array | None = None,
               mesh: SkinnedMesh | None = None) -> Iterator[NDArray[np.uint8]]:
        """Frames ``(H, W, 3)`` uint8 for poses given by forward kinematics ``(T, J, 4)``, ``(T, J, 3)``.

        ``floor_shift``: ``(T,)`` metres to move the ground along -Z per frame (a treadmill under an in-place walk);
        ``mesh``: the same body skinned otherwise (a clip's render settings, e.g. fewer influences per vertex;
        same vertices and faces), default the renderer's.
        """
        skin = self.mesh if mesh is None else mesh
        shifts = np.zeros(len(world_rotations)) if floor_shift is None else np.asarray(floor_shift)
        for rot, pos, shift in zip(world_rotations, world_positions, shifts, strict=True):
            v, n = skin.skin(skin.skinning_matrices(rot, pos))
            self._renderer._platform.make_current()
            self._upload(v, n)
            pose = np.eye(4)
            pose[2, 3] = -shift
            self.scene.set_pose(self._floor, pose)
            color, _ = self._renderer.render(self.scene, flags=self._flags)
            self._uploaded = True
            yield np.ascontiguousarray(color[..., :3])

    def close(self) -> None:
        """Free the GL resources and the context: pyrender's ``OffscreenRenderer.delete`` without the full
        ``gc.collect()`` it ends with (0.1-0.5 s in a process with a large heap, a server's or a test run's, once
        per rendered clip; 37 s of the test suite's sampled time)."""
        offscreen = self._renderer
        offscreen._platform.make_current()
        offscreen._renderer.delete()
        # Its delete() leaves the shadow framebuffer's id set: the renderer's __del__ (which deletes again) would
        # free that id in whichever context is current when the object is collected.
        offscreen._renderer._shadow_fb = None
        offscreen._platform.delete_context()
        offscreen._renderer = offscreen._platform = None
