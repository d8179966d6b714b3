"""The bytes of a glTF 2.0 file: the JSON parsed (pygltflib), buffers found (the binary chunk, ``data:`` URIs,
files beside it and never outside its folder) and accessors decoded to float64 arrays, every step bounded and
checked.  What the nodes, skins and animations mean is :mod:`anim_core.io.gltf`'s."""

from __future__ import annotations

import base64
import warnings
from pathlib import Path

import numpy as np
import pygltflib
from numpy.typing import NDArray

Array = NDArray[np.float64]

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


class GltfError(ValueError):
    """A glTF file that cannot be read as a skinned character or written."""


class GltfReader:
    """One glTF file opened: ``gltf`` its parsed JSON, :meth:`accessor` its arrays; at most ``max_values``
    numbers decoded from all accessors together; :meth:`fail` an error naming the file."""

    def __init__(self, path: Path, max_values: int) -> None:
        self.path = path
        self.name = path.name
        self.max_values = max_values  # numbers all accessors together may decode to
        self.values = 0
        try:
            with warnings.catch_warnings():  # pygltflib warns (and then fails) on bad headers; the error says it
                warnings.simplefilter("ignore")
                self.gltf = pygltflib.GLTF2().load(str(path))
        except Exception as exc:  # pygltflib raises bare exceptions of many kinds on malformed files
            raise GltfError(f"{self.name}: not a readable glTF 2.0 file ({type(exc).__name__}: {exc})") from None
        if self.gltf is None:
            raise GltfError(f"{self.name}: not a readable glTF 2.0 file")
        self._buffers: dict[int, bytes] = {}

    def fail(self, message: str) -> GltfError:
        return GltfError(f"{self.name}: {message}")

    def buffer(self, index: int) -> bytes:
        if index in self._buffers:
            return self._buffers[index]
        try:
            buf = self.gltf.buffers[index]
        except (IndexError, TypeError):
            raise self.fail(f"buffer {index} does not exist") from None
        if buf.uri is None:
            data = self.gltf.binary_blob()
            if data is None:
                raise self.fail(f"buffer {index} has no uri and the file has no binary chunk")
        elif buf.uri.startswith("data:"):
            try:
                data = base64.b64decode(buf.uri.split(",", 1)[1], validate=True)
            except (IndexError, ValueError):
                raise self.fail(f"buffer {index} has a malformed data uri") from None
        else:
            target = (self.path.parent / buf.uri).resolve()
            if self.path.parent.resolve() not in target.parents:
                raise self.fail(f"buffer {index} points outside the file's folder ({buf.uri!r})")
            try:
                data = target.read_bytes()
            except OSError:
                raise self.fail(f"external buffer {buf.uri!r} does not exist or cannot be read") from None
        if len(data) < (buf.byteLength or 0):
            raise self.fail(f"buffer {index} holds {len(data)} bytes, fewer than its byteLength {buf.byteLength}")
        self._buffers[index] = data
        return data

    def accessor(self, index: int | None, what: str) -> Array:
        """The accessor's elements as float64 ``(count, width)`` (normalized integers scaled to 0..1)."""
        try:
            acc = self.gltf.accessors[index]  # type: ignore[index]
            view = self.gltf.bufferViews[acc.bufferView]
        except (IndexError, TypeError):
            raise self.fail(f"{what}: accessor {index} or its buffer view does not exist") from None
        dtype = _COMPONENTS.get(acc.componentType)
        width = _WIDTH.get(acc.type)
        if dtype is None or width is None:
            raise self.fail(f"{what}: unsupported accessor type {acc.type} / component {acc.componentType}")
        item = np.dtype(dtype).itemsize
        if view.byteStride is not None and view.byteStride < item * width:
            # Elements may not overlap (glTF 2.0: byteStride >= element size); overlapping ones would let a few
            # bytes of buffer stand for millions of elements.
            raise self.fail(f"{what}: buffer view {acc.bufferView} has byteStride {view.byteStride}, less than the "
                            f"{item * width} bytes of one {acc.type} element")
        if acc.count is None or acc.count < 0:
            raise self.fail(f"{what}: accessor {index} has no valid count")
        self.values += acc.count * width
        if self.values > self.max_values:
            raise self.fail(f"{what}: the accessors hold more than the {self.max_values} numbers allowed here")
        stride = view.byteStride or item * width
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        need = start + stride * (acc.count - 1) + item * width if acc.count else start
        data = self.buffer(view.buffer)
        if need > len(data) or need > (view.byteOffset or 0) + view.byteLength:
            raise self.fail(f"{what}: accessor {index} reads past the end of its buffer (truncated file?)")
        raw = np.ndarray((acc.count, width), dtype=dtype, buffer=data, offset=start, strides=(stride, item))
        out = raw.astype(np.float64)
        if acc.normalized and dtype is not np.float32:
            out /= np.iinfo(dtype).max
        if not np.all(np.isfinite(out)):
            raise self.fail(f"{what}: accessor {index} holds NaN or infinite values")
        return out
