"""glTF 2.0 (``.glb``, ``.gltf``) skinned characters and animations, read and written with pygltflib.

Conventions: glTF is Y up, metres, quaternions ``(x, y, z, w)`` in the file; here, as everywhere in anim_core,
``(w, x, y, z)``.  A skin's joints become a :class:`~anim_core.math.skeleton.Skeleton` in topological order (parents
first; the skin's own order is kept in :attr:`GltfAsset.skin_order`): ``offsets`` are the joint nodes'
translations, ``rest_rotations`` their rotations, and the root joint takes the whole transform of the nodes above
it (a uniform scale there scales the skeleton, its motion and the inverse bind matrices).  Joint scales other than 1
are rejected (the skeleton has no scale).  Vertex influences are read from
``JOINTS_0``/``WEIGHTS_0`` and ``JOINTS_1``/``WEIGHTS_1`` (up to 8) and renormalised.

An animation becomes local rotations ``(F, J, 4)`` and a root translation ``(F, 3)`` (relative to the root's
rest ``offsets[0]``, as :meth:`Skeleton.forward_kinematics` takes it), sampled at a uniform rate: the rate of its
keys when they are evenly spaced, else ``fps``.  ``LINEAR`` keys are interpolated (slerp for rotations),
``STEP`` keys held, ``CUBICSPLINE`` keys taken at their values and interpolated linearly.

Files as exporters write them (COLLADA2GLTF, for one):

- **Translation keys on joints below the root** are accepted when they are still
  (:func:`~anim_core.io.bvh.still_translation`, the rule the BVH reader applies to position channels: they move
  about their mean by at most :data:`~anim_core.io.bvh.STILL_SHARE` = 1 % of its length); the mean is then that
  joint's translation in the animation (:attr:`GltfAnimation.offsets`), as a BVH's constant position channels set
  its offset.  Keys that move a joint more are refused with the joint named.  **Scale keys** within
  :data:`~anim_core.io.bvh.STILL_SHARE` of 1 (the rest scale) are accepted and ignored; others are refused.
- **One animation per joint**: when a file holds several animations and none of them keys more than one joint of
  the skin (and no joint's rotation, translation or scale is keyed by two of them), they are parts of one motion
  and read as one animation named ``first..last`` (``animation0..animation30``), on the time base of all their
  keys; :attr:`GltfAnimation.parts` lists them.  Animations that key no joint of the skin are left out then.
- **Unnamed joints** are named ``joint<k>``, ``k`` the joint's index in the skeleton's depth-first order from the
  root joint, children in the file's order (not the node index, not the skin's order).
- ``read_gltf(path, animations=False)`` reads the character alone (skin, bind pose, mesh): a character is read
  from its inverse bind matrices whatever animations the file holds.

Every failure is a :class:`GltfError` naming the file; nothing is written unless the whole file could be built.
"""

from __future__ import annotations

import base64
import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib
from numpy.typing import NDArray

from ..math.quat import identity, quat_from_matrix, quat_mul, rotate, slerp
from ..math.skeleton import Skeleton
from ..math.skinning import vertex_normals
from .bvh import STILL_SHARE, still_translation
from .gltf_buffers import GltfError, GltfReader

Array = NDArray[np.float64]

MAX_JOINTS = 1000
MAX_KEYS = 500_000
#: Sampled frames × joints of an animation read by default, and (× :data:`VALUES_PER_FRAME_JOINT`) the numbers all
#: accessors may decode to: uneven key times are resampled at ``fps``, so keys at 0, 1 and 16666 s on a 1000-joint
#: skin asked for 15 GiB.  Callers reading untrusted files pass a bound of their own (``max_frame_joints``).
MAX_FRAME_JOINTS = 20_000_000
VALUES_PER_FRAME_JOINT = 8
MAX_INFLUENCES = 8


@dataclass(frozen=True, eq=False)
class GltfAnimation:
    """One animation: ``times`` ``(F,)`` seconds from 0, ``rotations`` ``(F, J, 4)`` local (w, x, y, z),
    ``root_translation`` ``(F, 3)`` relative to the root's rest offset; ``offsets`` ``(J, 3)`` the joints'
    translations in this animation where its still translation keys set them (else ``None``: the skeleton's);
    ``parts``: the names of the file's animations read as this one (one-joint animations, see the module
    docstring), else ``()``."""

    name: str
    times: Array
    rotations: Array
    root_translation: Array
    offsets: Array | None = None
    parts: tuple[str, ...] = ()

    @property
    def frame_time(self) -> float:
        return float(self.times[1] - self.times[0]) if len(self.times) > 1 else 1.0 / 30.0


@dataclass(frozen=True, eq=False)
class GltfAsset:
    """A skinned character: ``skeleton``, mesh ``vertices``/``normals`` ``(V, 3)``, triangle ``faces`` ``(T, 3)``,
    influences ``joints``/``weights`` ``(V, 8)`` (skeleton indices), ``inverse_bind`` ``(J, 4, 4)`` (skeleton
    order), ``animations`` and ``skin_order`` (skeleton index of each joint in the skin's list)."""

    source: str
    skeleton: Skeleton
    vertices: Array
    normals: Array
    faces: NDArray[np.intp]
    joints: NDArray[np.intp]
    weights: Array
    inverse_bind: Array
    animations: tuple[GltfAnimation, ...]
    skin_order: NDArray[np.intp]


def _xyzw(q: Array) -> Array:
    return np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def _wxyz(q: Array) -> Array:
    return np.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def _node_trs(r: GltfReader, node: pygltflib.Node) -> tuple[Array, Array, Array]:
    """Translation ``(3,)``, unit rotation ``(4,)`` (w, x, y, z) and scale ``(3,)`` of ``node``; a rotation that is
    no quaternion (not 4 numbers, or all 0) or a matrix with a zero column fails naming the node."""
    if node.matrix is not None:
        m = np.array(node.matrix, dtype=np.float64).reshape(4, 4).T  # glTF matrices are column-major
        t = m[:3, 3]
        s = np.linalg.norm(m[:3, :3], axis=0)
        if not np.all(s > 0):
            raise r.fail(f"node {node.name!r} has a matrix with a zero column (no rotation has one)")
        return t, quat_from_matrix(m[:3, :3] / s), s
    t = np.array(node.translation if node.translation is not None else [0, 0, 0], np.float64)
    q = np.array(node.rotation if node.rotation is not None else [0, 0, 0, 1], np.float64)
    s = np.array(node.scale if node.scale is not None else [1, 1, 1], np.float64)
    if q.shape != (4,) or not np.linalg.norm(q) > 0:
        raise r.fail(f"node {node.name!r} has rotation {node.rotation}, not a quaternion (4 numbers, not all 0)")
    rotation = _wxyz(q)
    return t, rotation / np.linalg.norm(rotation), s


def read_gltf(path: str | os.PathLike[str], fps: float = 30.0, max_frame_joints: int = MAX_FRAME_JOINTS,
              animations: bool = True) -> GltfAsset:
    """Read the first skin of a ``.glb``/``.gltf`` file with every mesh bound to it, and all its animations (see
    module docstring; ``animations=False``: none, for a character).  An animation sampled to more than
    ``max_frame_joints`` frames × joints, or accessors decoding to more than :data:`VALUES_PER_FRAME_JOINT` times
    as many numbers, fail before the memory is taken."""
    try:
        return _read_gltf(Path(path), fps, max_frame_joints, animations)
    except GltfError:
        raise
    except (IndexError, KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        # A file whose parts do not fit together in a way no check above foresaw (found by tests/test_fuzz_readers.py:
        # empty influences beside full ones, indices into empty arrays): still the reader's own error, never a crash.
        raise GltfError(f"{Path(path).name}: malformed glTF ({type(exc).__name__}: {exc})") from None


def _read_gltf(path: Path, fps: float, max_frame_joints: int, with_animations: bool = True) -> GltfAsset:
    r = GltfReader(path, VALUES_PER_FRAME_JOINT * max_frame_joints)
    g = r.gltf
    nodes = g.nodes or []
    parent = _node_parents(r, nodes)
    if not g.skins:
        raise r.fail("has no skin: a character needs a skinned mesh (mesh, skin, joints, inverse bind matrices)")
    skin = g.skins[0]
    skin_joints = list(skin.joints or [])
    order = _skin_joint_order(r, nodes, parent, skin_joints)
    node_to_joint = {n: k for k, n in enumerate(order)}
    names = [nodes[n].name or f"joint{k}" for k, n in enumerate(order)]
    if len(set(names)) != len(names):
        raise r.fail("joint names are not unique")
    trs = [_node_trs(r, nodes[n]) for n in order]
    for k, (_, _, s) in enumerate(trs):
        if np.abs(s - 1.0).max() > 1e-4:
            raise r.fail(f"joint {names[k]!r} has scale {s.tolist()}; only unscaled joints are supported: "
                         f"apply the scale to the rig before exporting (Blender: Object > Apply > Scale in the "
                         f"rest pose)")
    offsets = np.array([t for t, _, _ in trs])
    rest = np.array([q for _, q, _ in trs])
    above_pos, above_rot, above_scale = above = _above_root(r, nodes, parent, order[0])
    offsets *= above_scale
    offsets[0] = above_pos + rotate(above_rot, offsets[0])
    rest[0] = quat_mul(above_rot, rest[0])
    skeleton = Skeleton(names, [node_to_joint.get(int(parent[n]), -1) for n in order], offsets, rest)
    skin_order = np.array([node_to_joint[n] for n in skin_joints], dtype=np.intp)

    if skin.inverseBindMatrices is None:
        raise r.fail("its skin has no inverse bind matrices")
    ibm = r.accessor(skin.inverseBindMatrices, "inverse bind matrices")
    if ibm.shape != (len(skin_joints), 16):
        raise r.fail(f"its skin has {len(skin_joints)} joints but {ibm.shape[0]} inverse bind matrices")
    inverse_bind = np.empty((len(order), 4, 4))
    inverse_bind[skin_order] = ibm.reshape(-1, 4, 4).transpose(0, 2, 1)
    inverse_bind[:, :3] *= above_scale  # diag(s, s, s, 1) @ IBM: the rigid skeleton's joint frames carry no scale

    # Every mesh bound to the skin is part of the body (characters often come as body, eyes, teeth, hair).
    mesh_indices = list(dict.fromkeys(n.mesh for n in nodes if n.skin == 0 and n.mesh is not None))
    if not mesh_indices:
        raise r.fail("no node uses the skin with a mesh")
    if any(not 0 <= m < len(g.meshes) for m in mesh_indices):
        raise r.fail("a node uses a mesh that does not exist")
    vertices, normals, faces, joints, weights = [], [], [], [], []
    base = 0
    primitives = [prim for m in mesh_indices for prim in g.meshes[m].primitives]
    for p, prim in enumerate(primitives):
        v, nn, tri, jj, ww = _read_primitive(r, p, prim, skin_order)
        vertices.append(v)
        normals.append(nn)
        faces.append(tri + base)
        joints.append(jj)
        weights.append(ww)
        base += len(v)
    animations = _read_animations(r, node_to_joint, skeleton, above, fps, max_frame_joints) \
        if with_animations else ()
    return GltfAsset(r.name, skeleton, np.concatenate(vertices), np.concatenate(normals),
                     np.concatenate(faces), np.concatenate(joints), np.concatenate(weights), inverse_bind,
                     animations, skin_order)


def _node_parents(r: GltfReader, nodes: list[pygltflib.Node]) -> NDArray[np.intp]:
    """Parent of every node (-1: none); a shared child or a cycle fails here, so walks up the tree end."""
    parent = np.full(len(nodes), -1, dtype=np.intp)
    for i, node in enumerate(nodes):
        for c in node.children or []:
            if not 0 <= c < len(nodes):
                raise r.fail(f"node {i} has a child {c} that does not exist")
            if parent[c] >= 0 or c == i:
                raise r.fail(f"node {c} has two parents or is its own child (the node tree has a cycle)")
            parent[c] = i
    for i in range(len(nodes)):
        seen, j = set(), i
        while j >= 0:
            if j in seen:
                raise r.fail(f"the node tree has a cycle through node {j} ({nodes[j].name!r})")
            seen.add(j)
            j = int(parent[j])
    return parent


def _skin_joint_order(r: GltfReader, nodes: list[pygltflib.Node], parent: NDArray[np.intp],
                      skin_joints: list[int]) -> list[int]:
    """The skin's joint nodes in topological order: depth-first from its one root joint, children in file order."""
    if not skin_joints:
        raise r.fail("its skin has no joints")
    if len(skin_joints) > MAX_JOINTS:
        raise r.fail(f"its skin has {len(skin_joints)} joints; at most {MAX_JOINTS} are supported")
    if len(set(skin_joints)) != len(skin_joints) or any(not 0 <= j < len(nodes) for j in skin_joints):
        raise r.fail("its skin lists a joint twice or a joint node that does not exist")
    in_skin = set(skin_joints)
    roots = [j for j in skin_joints if parent[j] not in in_skin]
    if len(roots) != 1:
        raise r.fail(f"its skin's joints form {len(roots)} trees ({[nodes[j].name for j in roots]}); one root "
                     f"joint is needed")
    order: list[int] = []
    stack = [roots[0]]
    while stack:
        j = stack.pop()
        order.append(j)
        stack.extend(reversed([c for c in nodes[j].children or [] if c in in_skin]))
    if len(order) != len(skin_joints):
        raise r.fail("some skin joints are not below the root joint through other joints")
    return order


def _above_root(r: GltfReader, nodes: list[pygltflib.Node], parent: NDArray[np.intp],
                root: int) -> tuple[Array, Array, float]:
    """(translation ``(3,)``, rotation ``(4,)``, uniform scale) of the nodes above the ``root`` joint node.

    The root takes this transform.  A uniform scale there (Blender's "Armature" at 0.01 over a rig in centimetres,
    as Mixamo characters come) scales the whole skeleton: every offset, the root's motion, and the inverse bind
    matrices, which then carry the inverse scale."""
    above_rot, above_pos, above_scale = identity(), np.zeros(3), 1.0
    j = int(parent[root])
    while j >= 0:
        t, q, s = _node_trs(r, nodes[j])
        if not (s.min() > 0 and np.ptp(s) <= 1e-4 * s.max()):
            # A non-uniform scale stretches each bone by how it is turned, which changes as it moves: no skeleton of
            # rigid bones (this one, the character's) can play that.
            raise r.fail(f"node {nodes[j].name!r} above the skeleton has scale {s.tolist()}; only a uniform "
                         f"positive scale is supported there (a non-uniform or mirroring scale stretches the bones "
                         f"as they turn). Apply the scale to the rig before exporting (Blender: select the "
                         f"armature, Object > Apply > Scale) and export again")
        above_pos, above_rot = t + s[0] * rotate(q, above_pos), quat_mul(q, above_rot)
        above_scale *= float(s[0])
        j = int(parent[j])
    return above_pos, above_rot, above_scale


def _read_primitive(r: GltfReader, p: int, prim: pygltflib.Primitive,
                    skin_order: NDArray[np.intp]) -> tuple[Array, Array, NDArray[np.intp], NDArray[np.intp], Array]:
    """Mesh primitive ``p``: vertices and normals ``(V, 3)``, faces ``(T, 3)`` indexing its own vertices, and
    influences ``(V, 8)`` (skeleton indices, weights renormalised)."""
    mode = 4 if prim.mode is None else prim.mode
    if mode != 4:
        raise r.fail(f"mesh primitive {p} has mode {mode}; only triangles (mode 4) are supported")
    a = prim.attributes
    if a.POSITION is None or a.JOINTS_0 is None or a.WEIGHTS_0 is None:
        raise r.fail(f"mesh primitive {p} lacks POSITION, JOINTS_0 or WEIGHTS_0")
    extra = sorted(k for k, v in vars(a).items() if v is not None and k.startswith(("JOINTS_", "WEIGHTS_"))
                   and k.split("_")[-1].isdigit() and int(k.split("_")[-1]) >= 2)
    if extra:
        raise r.fail(f"mesh primitive {p} has more than {MAX_INFLUENCES} influences per vertex ({extra[0]}); "
                     f"at most {MAX_INFLUENCES} (JOINTS_0/1, WEIGHTS_0/1) are supported")
    v = r.accessor(a.POSITION, f"primitive {p} positions")
    n_v = len(v)
    idx = r.accessor(prim.indices, f"primitive {p} indices").astype(np.intp).reshape(-1) \
        if prim.indices is not None else np.arange(n_v)
    if len(idx) % 3 or (len(idx) and (idx.min() < 0 or idx.max() >= n_v)):
        raise r.fail(f"mesh primitive {p}: indices are not whole triangles of existing vertices")
    jw = [(r.accessor(a.JOINTS_0, "joints"), r.accessor(a.WEIGHTS_0, "weights"))]
    # pygltflib only has the attributes a file names: exporters writing <= 4 influences have no JOINTS_1.
    joints_1, weights_1 = getattr(a, "JOINTS_1", None), getattr(a, "WEIGHTS_1", None)
    if joints_1 is not None and weights_1 is not None:
        jw.append((r.accessor(joints_1, "joints"), r.accessor(weights_1, "weights")))
    jj = np.concatenate([x for x, _ in jw], axis=1)
    ww = np.concatenate([w for _, w in jw], axis=1)
    if jj.shape[0] != n_v or ww.shape != jj.shape or (jj.size and jj.max() >= len(skin_order)):
        raise r.fail(f"mesh primitive {p}: influences do not match the vertices or name missing joints")
    if np.any(ww < 0) or np.any(ww.sum(axis=1) <= 0):
        raise r.fail(f"mesh primitive {p}: some vertices have no positive skin weight")
    nn = r.accessor(a.NORMAL, "normals") if a.NORMAL is not None else None
    if nn is None:
        nn = vertex_normals(v, idx.reshape(-1, 3))
    pad = MAX_INFLUENCES - jj.shape[1]
    jj = np.pad(skin_order[jj.astype(np.intp)], ((0, 0), (0, pad)))
    ww = np.pad(ww / ww.sum(axis=1, keepdims=True), ((0, 0), (0, pad)))
    return v, nn, idx.reshape(-1, 3), jj, ww


def _sample(times: Array, values: Array, t: Array, interpolation: str, rotation: bool) -> Array:
    if interpolation == "CUBICSPLINE":
        values = values.reshape(len(times), 3, -1)[:, 1]
    if len(times) == 1:
        return np.repeat(values[:1], len(t), axis=0)
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    u = np.clip((t - times[k]) / np.maximum(times[k + 1] - times[k], 1e-12), 0.0, 1.0)
    if interpolation == "STEP":
        u = np.where(u >= 1.0, 1.0, 0.0)
    if rotation:
        return slerp(values[k], values[k + 1], u)
    return values[k] + (values[k + 1] - values[k]) * u[:, None]


_Channel = tuple[int, str, Array, Array, str, str]  # joint, path, key times, key values, interpolation, animation


def _channels(r: GltfReader, anim: pygltflib.Animation, name: str, node_to_joint: dict[int, int]) -> list[_Channel]:
    """The channels of ``anim`` that key a joint of the skin (rotation, translation, scale), keys checked."""
    channels = []
    for c in anim.channels:
        if c.target.node not in node_to_joint or c.target.path not in ("rotation", "translation", "scale"):
            continue
        try:
            sampler = anim.samplers[c.sampler]
        except (IndexError, TypeError):
            raise r.fail(f"animation {name!r} uses a sampler that does not exist") from None
        times = r.accessor(sampler.input, f"animation {name!r} key times")[:, 0]
        values = r.accessor(sampler.output, f"animation {name!r} key values")
        if len(times) > MAX_KEYS:
            raise r.fail(f"animation {name!r} has {len(times)} keys; at most {MAX_KEYS} are supported")
        if len(times) == 0 or np.any(np.diff(times) <= 0):
            raise r.fail(f"animation {name!r}: key times are empty or not increasing")
        channels.append((node_to_joint[c.target.node], c.target.path, times, values, sampler.interpolation, name))
    return channels


def _read_animations(r: GltfReader, node_to_joint: dict[int, int], skeleton: Skeleton,
                     above: tuple[Array, Array, float], fps: float,
                     max_frame_joints: int) -> tuple[GltfAnimation, ...]:
    """Every animation of the file, or its one-joint animations as one (see the module docstring)."""
    found = []
    for k, anim in enumerate(r.gltf.animations or []):
        name = anim.name or f"animation{k}"
        found.append((name, _channels(r, anim, name, node_to_joint)))
    keyed = [(name, channels) for name, channels in found if channels]
    targets = [(j, path) for _, channels in keyed for j, path, *_ in channels]
    if (len(keyed) > 1 and all(len({ch[0] for ch in channels}) == 1 for _, channels in keyed)
            and len(set(targets)) == len(targets)):
        # COLLADA2GLTF writes one animation per joint (animation0..N, on a shared time base): no part of it is a
        # motion by itself, all of them are one.
        names = tuple(name for name, _ in keyed)
        merged = _build_animation(r, f"{names[0]}..{names[-1]}", [ch for _, chs in keyed for ch in chs], skeleton,
                                  above, fps, max_frame_joints)
        return (dataclasses.replace(merged, parts=names),)
    out = []
    for name, channels in found:
        if not channels:
            raise r.fail(f"animation {name!r} animates no joint of the skin")
        out.append(_build_animation(r, name, channels, skeleton, above, fps, max_frame_joints))
    return tuple(out)


def _build_animation(r: GltfReader, name: str, channels: list[_Channel], skeleton: Skeleton,
                     above: tuple[Array, Array, float], fps: float,
                     max_frame_joints: int = MAX_FRAME_JOINTS) -> GltfAnimation:
    """One animation on ``skeleton`` from its ``channels``; ``above``: (translation, rotation, uniform scale) of
    the nodes above the root joint, which the root's channels are in."""
    above_pos, above_rot, above_scale = above
    start = min(ch[2][0] for ch in channels)
    end = max(ch[2][-1] for ch in channels)
    steps = np.concatenate([np.diff(ch[2]) for ch in channels if len(ch[2]) > 1] or [np.array([1.0 / fps])])
    step = float(np.median(steps))
    if np.allclose(steps, step, rtol=1e-3):
        fps = 1.0 / step
    # Key times are float32: a whole number of frames may come out a few 1e-5 frames short.
    n = int(np.floor((end - start) * fps + 1e-3)) + 1
    if n > MAX_KEYS:
        raise r.fail(f"animation {name!r} would have {n} frames; at most {MAX_KEYS} are supported")
    if n * skeleton.n_joints > max_frame_joints:
        raise r.fail(f"animation {name!r} would have {n} frames of {skeleton.n_joints} joints (its keys span "
                     f"{end - start:g} s at {fps:g} fps), more than the {max_frame_joints} frame-joints allowed here")
    t = start + np.arange(n) / fps
    rot = np.broadcast_to(skeleton.rest_rotations, (n, skeleton.n_joints, 4)).copy()
    root = np.zeros((n, 3))
    offsets = skeleton.offsets.copy()
    for joint, path, times, values, interp, part in channels:
        if path == "rotation":
            rot[:, joint] = _wxyz(_sample(times, values, t, interp or "LINEAR", True))
            if joint == 0:
                rot[:, 0] = quat_mul(above_rot, rot[:, 0])
        elif path == "scale":
            # Rigid bones have no scale: keys that restate the rest's 1 (to exporter rounding) are no motion.
            keys = values.reshape(len(times), 3, -1)[:, 1] if interp == "CUBICSPLINE" else values
            off = float(np.abs(keys - 1.0).max())
            if off > STILL_SHARE:
                raise r.fail(f"animation {part!r} scales joint {skeleton.names[joint]!r} (by up to {1 + off:g}); "
                             f"only scales within {STILL_SHARE:.0%} of 1 are supported: bake the scale into "
                             f"the rig before exporting")
        elif joint == 0:
            local = _sample(times, values, t, interp or "LINEAR", False)
            root = above_pos + above_scale * rotate(above_rot, local) - skeleton.offsets[0]
        else:
            keys = above_scale * (values.reshape(len(times), 3, -1)[:, 1] if interp == "CUBICSPLINE" else values)
            mean, spread, still = still_translation(keys)
            if not still:
                raise r.fail(f"animation {part!r} translates joint {skeleton.names[joint]!r} (it moves up to "
                             f"{spread:.3g} units about its mean); only the root may translate, other joints' "
                             f"translation keys must stay within {STILL_SHARE:.0%} of the bone's length: bake "
                             f"them into rotations")
            offsets[joint] = mean
    rot /= np.linalg.norm(rot, axis=-1, keepdims=True)
    moved = None if np.array_equal(offsets, skeleton.offsets) else offsets
    return GltfAnimation(name, t - start, rot, root, moved)


# ---------------------------------------------------------------------------------------------------------------
# Writing

class _Builder:
    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[pygltflib.BufferView] = []
        self.accessors: list[pygltflib.Accessor] = []

    def add(self, data: np.ndarray, kind: str, component: int, target: int | None = None,
            bounds: bool = False) -> int:
        raw = np.ascontiguousarray(data).tobytes()
        while len(self.blob) % 4:
            self.blob.append(0)
        self.views.append(pygltflib.BufferView(buffer=0, byteOffset=len(self.blob), byteLength=len(raw),
                                               target=target))
        self.blob.extend(raw)
        flat = data.reshape(len(data), -1)
        self.accessors.append(pygltflib.Accessor(
            bufferView=len(self.views) - 1, componentType=component, count=len(data), type=kind,
            min=flat.min(axis=0).tolist() if bounds else None, max=flat.max(axis=0).tolist() if bounds else None))
        return len(self.accessors) - 1


def write_gltf(path: str | os.PathLike[str], skeleton: Skeleton, vertices: Array, normals: Array,
               faces: NDArray[np.intp], joints: NDArray[np.intp], weights: Array, inverse_bind: Array,
               animations: tuple[GltfAnimation, ...] = ()) -> None:
    """Write a skinned character with animations as ``.glb`` (binary) or ``.gltf`` (buffer embedded).

    ``inverse_bind``: ``(J, 4, 4)`` or ``(J, 3, 4)``; ``joints``/``weights``: ``(V, K)``, ``K <= 8``.  The file is
    written to a temporary name and renamed, so a failure leaves nothing behind.
    """
    path = Path(path)
    if path.suffix not in (".glb", ".gltf"):
        raise GltfError(f"{path.name}: a glTF file name ends with .glb or .gltf")
    n = skeleton.n_joints
    ib = np.asarray(inverse_bind, np.float64)
    if ib.shape == (n, 3, 4):
        ib = np.concatenate([ib, np.broadcast_to([0.0, 0.0, 0.0, 1.0], (n, 1, 4))], axis=1)
    for what, values in (("vertices", vertices), ("normals", normals), ("weights", weights),
                         ("inverse bind matrices", ib), ("skeleton offsets", skeleton.offsets),
                         *((f"animation {a.name!r}", np.concatenate([a.rotations.ravel(), a.root_translation.ravel(),
                                                                     a.times])) for a in animations)):
        if not np.all(np.isfinite(values)):
            raise GltfError(f"{path.name}: {what} hold NaN or infinite values")
    k = joints.shape[1]
    if k > MAX_INFLUENCES:
        raise GltfError(f"{path.name}: at most {MAX_INFLUENCES} influences per vertex")
    jj = np.zeros((len(vertices), 8), np.uint16)
    ww = np.zeros((len(vertices), 8), np.float32)
    jj[:, :k] = np.where(weights > 0, joints, 0)
    ww[:, :k] = weights
    b = _Builder()
    attributes = pygltflib.Attributes(
        POSITION=b.add(np.asarray(vertices, np.float32), "VEC3", 5126, 34962, bounds=True),
        NORMAL=b.add(np.asarray(normals, np.float32), "VEC3", 5126, 34962),
        JOINTS_0=b.add(jj[:, :4].copy(), "VEC4", 5123, 34962), WEIGHTS_0=b.add(ww[:, :4].copy(), "VEC4", 5126, 34962),
        JOINTS_1=b.add(jj[:, 4:].copy(), "VEC4", 5123, 34962), WEIGHTS_1=b.add(ww[:, 4:].copy(), "VEC4", 5126, 34962))
    indices = b.add(np.asarray(faces, np.uint32).reshape(-1), "SCALAR", 5125, 34963)
    ibm = b.add(ib.transpose(0, 2, 1).reshape(n, 16).astype(np.float32), "MAT4", 5126)
    nodes = []
    for j in range(n):
        nodes.append(pygltflib.Node(
            name=skeleton.names[j], translation=skeleton.offsets[j].tolist(),
            rotation=_xyzw(skeleton.rest_rotations[j]).tolist(), children=skeleton.children(j) or None))
    nodes.append(pygltflib.Node(name="mesh", mesh=0, skin=0))
    gl_anims = []
    for anim in animations:
        if anim.rotations.shape != (len(anim.times), n, 4) or anim.root_translation.shape != (len(anim.times), 3):
            raise GltfError(f"{path.name}: animation {anim.name!r} does not fit the skeleton")
        t = b.add(np.asarray(anim.times, np.float32)[:, None], "SCALAR", 5126, bounds=True)
        samplers, channels = [], []
        for j in range(n):
            out = b.add(_xyzw(anim.rotations[:, j]).astype(np.float32), "VEC4", 5126)
            samplers.append(pygltflib.AnimationSampler(input=t, output=out, interpolation="LINEAR"))
            channels.append(pygltflib.AnimationChannel(sampler=j, target=pygltflib.AnimationChannelTarget(
                node=j, path="rotation")))
        out = b.add((anim.root_translation + skeleton.offsets[0]).astype(np.float32), "VEC3", 5126)
        samplers.append(pygltflib.AnimationSampler(input=t, output=out, interpolation="LINEAR"))
        channels.append(pygltflib.AnimationChannel(sampler=n, target=pygltflib.AnimationChannelTarget(
            node=0, path="translation")))
        gl_anims.append(pygltflib.Animation(name=anim.name, samplers=samplers, channels=channels))
    g = pygltflib.GLTF2(
        asset=pygltflib.Asset(generator="animstudy", version="2.0"), scene=0,
        scenes=[pygltflib.Scene(nodes=[0, n])], nodes=nodes,
        meshes=[pygltflib.Mesh(primitives=[pygltflib.Primitive(attributes=attributes, indices=indices, mode=4)])],
        skins=[pygltflib.Skin(joints=list(range(n)), inverseBindMatrices=ibm, skeleton=0)],
        animations=gl_anims, accessors=b.accessors, bufferViews=b.views,
        buffers=[pygltflib.Buffer(byteLength=len(b.blob))])
    tmp = path.with_name(path.name + ".part")
    try:
        if path.suffix == ".glb":
            g.set_binary_blob(bytes(b.blob))
            g.save_binary(str(tmp))
        else:
            g.buffers[0].uri = "data:application/octet-stream;base64," + base64.b64encode(bytes(b.blob)).decode()
            g.save_json(str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
