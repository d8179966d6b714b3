"""Hostile motion files built by the tests themselves (issue 26): small files that made the readers allocate
gigabytes.  Used by the upload tests and by ``python -m tests.hostile_files`` (peak memory of inspecting each).

- :func:`bvh_bomb`: the CMU idle rig plus 969 joints with ``CHANNELS 0``, 10,000 frames (~120 KB): a frame line
  holds only the root's six values, while every frame costs memory for all 1000 joints.
- :func:`gltf_key_bomb`: a 1000-joint skin whose animation has key times ``[0, 1, T]``: uneven keys are resampled
  at 30 fps, ``T * 30`` frames × 1000 joints (T = 16666: 14.9 GiB of rotations).
- :func:`gltf_stride_bomb`: inverse bind matrices with ``byteStride: 1`` and a count of 2M: each 64-byte matrix
  overlaps the next, so 2 MB of buffer give 2M matrices (256 MB as float64).
"""

from __future__ import annotations

import functools
import gzip
import json
import struct
import sys
import tempfile
from pathlib import Path

import numpy as np
import pygltflib

IDLE = "mocap/cmu/113_21_idle_30fps.bvh.gz"
CEILING = 6 << 30  # address space of the measuring process


def bvh_bomb(data: Path, extra_joints: int = 969, frames: int = 10_000) -> bytes:
    """The CMU idle rig (root channels only) with ``extra_joints`` channel-less joints and ``frames`` frames."""
    lines = gzip.decompress((data / IDLE).read_bytes()).decode().splitlines()
    at = lines.index("MOTION")
    hierarchy = []
    for k, line in enumerate(lines[:at]):
        if line.strip().startswith("CHANNELS") and k > 5:  # every joint but the root: no channels
            line = line[: len(line) - len(line.lstrip())] + "CHANNELS 0"
        hierarchy.append(line)
    # The extra joints hang below the root, before its closing brace (the last line of the hierarchy).
    extra = [f"\tJOINT extra{i}\n\t{{\n\t\tOFFSET 0 0 0\n\t\tCHANNELS 0\n\t}}" for i in range(extra_joints)]
    text = "\n".join([*hierarchy[:-1], *extra, hierarchy[-1], "MOTION", f"Frames: {frames}",
                      "Frame Time: 0.0333333", *(["0 0 0 0 0 0"] * frames)]) + "\n"
    return text.encode()


def _chain_gltf(path: Path, joints: int, times: list[float]) -> None:
    """A ``joints``-joint chain with one triangle and an animation keyed at ``times`` (written by write_gltf)."""
    from anim_core.io.gltf import GltfAnimation, write_gltf
    from anim_core.math.skeleton import Skeleton

    offsets = np.zeros((joints, 3))
    offsets[1:, 1] = 0.01
    skeleton = Skeleton([f"j{i}" for i in range(joints)], [-1, *range(joints - 1)], offsets)
    vertices = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]])
    normals = np.array([[0.0, 0, 1]] * 3)
    inverse_bind = np.broadcast_to(np.eye(4), (joints, 4, 4)).copy()
    n = len(times)
    rotations = np.zeros((n, joints, 4))
    rotations[..., 0] = 1.0
    write_gltf(path, skeleton, vertices, normals, np.array([[0, 1, 2]]), np.zeros((3, 1), np.intp),
               np.ones((3, 1)), inverse_bind, (GltfAnimation("bomb", np.array(times, float), rotations,
                                                             np.zeros((n, 3))),))


@functools.lru_cache(maxsize=2)
def _chain_glb(joints: int, times: tuple[float, ...]) -> bytes:
    """The bytes of :func:`_chain_gltf`'s file, made once per process (pygltflib takes about a second to write
    1000 joints)."""
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "chain.glb"
        _chain_gltf(path, joints, list(times))
        return path.read_bytes()


def _glb(document: dict, blob: bytes) -> bytes:
    """A ``.glb``: the 12-byte header, the JSON chunk (space-padded) and the binary chunk (zero-padded)."""
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    return (struct.pack("<4sII", b"glTF", 2, 28 + len(text) + len(blob)) + struct.pack("<I4s", len(text), b"JSON")
            + text + struct.pack("<I4s", len(blob), b"BIN\0") + blob)


def gltf_key_bomb(path: Path, last_key: float = 16666.0, joints: int = 1000) -> Path:
    """The key-time bomb as ``.glb`` at ``path``: keys at 0, 1 and ``last_key`` seconds (the last key time of the
    chain's animation rewritten in its binary chunk, and the accessor's ``max`` with it)."""
    data = _chain_glb(joints, (0.0, 1.0, 2.0))
    (json_length,) = struct.unpack_from("<I", data, 12)
    document = json.loads(data[20:20 + json_length])
    (blob_length,) = struct.unpack_from("<I", data, 20 + json_length)
    blob = bytearray(data[28 + json_length:28 + json_length + blob_length])
    acc = document["accessors"][document["animations"][0]["samplers"][0]["input"]]
    view = document["bufferViews"][acc["bufferView"]]
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    blob[start: start + 12] = struct.pack("<3f", 0.0, 1.0, last_key)
    acc["max"] = [last_key]
    path.write_bytes(_glb(document, bytes(blob)))
    return path


def gltf_stride_bomb(path: Path, count: int = 2_000_000) -> Path:
    """The stride bomb as ``.glb``: the inverse bind matrices' accessor claims ``count`` matrices 1 byte apart."""
    _chain_gltf(path, 3, [0.0, 1.0 / 30])
    g = pygltflib.GLTF2().load(str(path))
    blob = bytearray(g.binary_blob())
    while len(blob) % 4:
        blob.append(0)
    offset, length = len(blob), count - 1 + 64
    blob.extend(b"\0" * length)
    g.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=length, byteStride=1))
    g.accessors[g.skins[0].inverseBindMatrices] = pygltflib.Accessor(
        bufferView=len(g.bufferViews) - 1, componentType=5126, count=count, type="MAT4")
    g.buffers[0].byteLength = len(blob)
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(path))
    return path


def _peak_of_inspection(paths: list[Path]) -> None:
    """Inspect each file as an upload is (:func:`server.uploads.service.inspect_upload`) and print one JSON line
    each: the outcome, seconds, and the peak RSS (MiB, ``ru_maxrss`` of this process) before and after; the peak
    only grows, so ``added_mib`` of the last line bounds every file's."""
    import resource
    import time

    import server.uploads.service as service
    from server.errors import ServiceError

    # A ceiling for this measurement only, so that the unfixed readers (14.9 GiB asked) cannot take the machine.
    resource.setrlimit(resource.RLIMIT_AS, (CEILING, CEILING))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    for path in paths:
        t0 = time.perf_counter()
        try:
            service.inspect_upload(path)
            outcome = "accepted"
        except ServiceError as exc:
            outcome = f"{exc.status_code}: {exc.detail}"[:200]
        except MemoryError:
            outcome = f"MemoryError at the measurement's ceiling of {CEILING >> 20} MiB"
        seconds = time.perf_counter() - t0
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(json.dumps({"file": path.name, "bytes": path.stat().st_size, "outcome": outcome,
                          "seconds": round(seconds, 2), "rss_before_mib": round(before, 1),
                          "peak_rss_mib": round(peak, 1), "added_mib": round(peak - before, 1)}), flush=True)


def write_bombs(out: Path, data: Path) -> list[Path]:
    """The bomb files of issue 26 in ``out``: the BVH, the glTF key bombs (last key 1000 and 16666 s), the stride
    bomb."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "bomb.bvh").write_bytes(bvh_bomb(data))
    return [out / "bomb.bvh", gltf_key_bomb(out / "keys_1000.glb", 1000.0), gltf_key_bomb(out / "keys_16666.glb"),
            gltf_stride_bomb(out / "stride.glb")]


def main(argv: list[str]) -> int:
    """``python -m tests.hostile_files DIR`` writes the bomb files into DIR and measures inspecting each in its
    own process; ``python -m tests.hostile_files --inspect FILE...`` measures the files in one process."""
    import subprocess

    if argv[:1] == ["--inspect"]:
        _peak_of_inspection([Path(a) for a in argv[1:]])
        return 0
    data = Path(__file__).resolve().parents[1] / "data"
    for f in write_bombs(Path(argv[0]), data):
        subprocess.run([sys.executable, "-m", "tests.hostile_files", "--inspect", str(f)], check=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
