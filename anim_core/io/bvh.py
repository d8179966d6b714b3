"""Reading, writing and converting Biovision Hierarchy (BVH) motion files.

A BVH file has a ``HIERARCHY`` section (joints with ``OFFSET`` in the parent's frame, ``CHANNELS``, and
``End Site`` leaves) and a ``MOTION`` section with one line of channel values per frame.  Values are kept
exactly as read (``float64``, degrees for rotations, file units for positions); :meth:`Bvh.pose_arrays`
converts them to local quaternions (radians) for :class:`~anim_core.math.skeleton.Skeleton` forward kinematics.

Rotation channels of a joint are composed in the order listed, about the moving axes:
``Zrotation Yrotation Xrotation`` means ``R = Rz @ Ry @ Rx`` (``quat_from_euler(.., "ZYX")``).  Position
channels translate the joint in its parent's frame before the rotation.
"""

from __future__ import annotations

import gzip
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..math.clip import KeyframeClip, PlaybackMode
from ..math.quat import euler_from_quat, quat_from_euler
from ..math.skeleton import Skeleton

Array = NDArray[np.float64]

#: Limits checked while parsing, before memory is spent: a hostile or broken file fails fast with its line.
MAX_JOINTS = 10_000
MAX_FRAMES = 1_000_000
#: Relative tolerance within which a constant position channel equals the joint's OFFSET (it is then the bone).
OFFSET_MATCH = 1e-4
#: A joint's translation that moves about its mean by at most this share of the mean's length is *still*: an
#: exporter's rounding or a constant restated in keys, not motion (:func:`still_translation`).  The BVH reader
#: averages such position channels below the root (:func:`anim_core.rig.normalize.normalize_bvh`); the glTF reader
#: takes such translation keys as the joint's translation, and scale keys within this share of 1 as unscaled
#: (:func:`anim_core.io.gltf.read_gltf`).  One rule for both formats.
STILL_SHARE = 0.01
#: Below this share of a translation's length (at least 1 unit), differences are float rounding in any case.
ROUNDING_SHARE = 1e-6
#: Frames × joints read by default: every frame costs memory for every joint, channels or not (a few hundred bytes
#: per frame·joint by the time a motion is inspected), so a small file of channel-less joints and many frames could
#: otherwise ask for gigabytes.  Callers reading untrusted files pass a bound of their own (``max_frame_joints``).
MAX_FRAME_JOINTS = 20_000_000
CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")


class BvhError(ValueError):
    """Malformed BVH text or a pose that the file's channels cannot express.

    Parse errors name the source, the 1-based line number and what was expected vs found.
    """


def _fail(source: str, line: int, message: str) -> BvhError:
    return BvhError(f"{source}, line {line}: {message}")


def _fail_eof(source: str, line: int, message: str) -> BvhError:
    return BvhError(f"{source}, unexpected end of file after line {line}: {message}")


def _to_float(token: str) -> float | None:
    """The value of a finite decimal number token, else ``None`` (``float`` alone also takes '1_0', 'nan')."""
    try:
        value = float(token)
    except ValueError:
        return None
    return value if math.isfinite(value) and "_" not in token else None


class _Lines:
    """Non-blank lines with their 1-based numbers; CRLF/LF and any whitespace are accepted."""

    def __init__(self, text: str, source: str) -> None:
        self.source = source
        self.items = [(n, s.strip()) for n, s in enumerate(text.split("\n"), 1) if s.strip()]
        self.pos = 0
        self.last = 0  # number of the last line consumed, for end-of-file messages

    def next(self, expected: str) -> tuple[int, str, list[str]]:
        if self.pos >= len(self.items):
            raise _fail_eof(self.source, self.last, f"expected {expected}")
        number, line = self.items[self.pos]
        self.pos += 1
        self.last = number
        return number, line, line.split()

    def error(self, number: int, expected: str, line: str) -> BvhError:
        shown = line if len(line) <= 60 else line[:57] + "..."
        return _fail(self.source, number, f"expected {expected}, found {shown!r}")


def still_translation(translations: ArrayLike) -> tuple[Array, float, bool]:
    """``(mean, spread, still)`` of a joint's translations ``(F, 3)`` over time (file units): ``spread`` the largest
    coordinate difference of a frame from ``mean`` ``(3,)``; ``still`` when ``spread`` is at most
    :data:`STILL_SHARE` of the mean's length (or float rounding, :data:`ROUNDING_SHARE`)."""
    t = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
    mean = t.mean(axis=0)
    spread = float(np.abs(t - mean).max()) if len(t) else 0.0
    length = float(np.linalg.norm(mean))
    return mean, spread, spread <= max(STILL_SHARE * length, ROUNDING_SHARE * max(length, 1.0))


@dataclass(eq=False)
class Bvh:
    """Contents of a BVH file.

    ``skeleton``: joints in file order (topological), offsets from ``OFFSET`` in file units, identity rest
    rotations; ``channels``: per joint, channel names as in the file (0..6 of :data:`CHANNEL_NAMES`, any
    order); ``end_sites``: joint index -> End Site offset ``(3,)``; ``frame_time``: seconds per frame;
    ``motion``: ``(F, C)`` channel values in file order (degrees for rotations, file units for positions);
    ``source``: the file name, for error messages.
    """

    skeleton: Skeleton
    channels: tuple[tuple[str, ...], ...]
    end_sites: dict[int, Array]
    frame_time: float
    motion: Array
    source: str = "<bvh>"  # names the file in error messages

    def __post_init__(self) -> None:
        self.channels = tuple(tuple(c) for c in self.channels)
        self.motion = np.asarray(self.motion, dtype=np.float64)
        n_channels = sum(len(c) for c in self.channels)
        if len(self.channels) != self.skeleton.n_joints or self.motion.ndim != 2 \
                or self.motion.shape[1] != n_channels:
            raise ValueError(f"{self.skeleton.n_joints} joints with {n_channels} channels need channels for "
                             f"every joint and motion (F, {n_channels}), got {len(self.channels)} channel "
                             f"lists and motion {self.motion.shape}")

    @property
    def n_frames(self) -> int:
        return self.motion.shape[0]

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def _columns(self) -> tuple[dict[str, tuple[NDArray[np.intp], NDArray[np.intp]]], NDArray[np.intp]]:
        """Motion column per joint and axis, ``-1`` where the channel is missing.

        Returns rotation groups ``{order: (joints (G,), columns (G, 3))}``, where ``order`` lists the joint's
        rotation axes first and then the missing ones (so missing angles are last, and zero), and position
        columns ``(J, 3)``.  Runs once per joint, on metadata only.
        """
        groups: dict[str, tuple[list[int], list[list[int]]]] = {}
        positions = np.full((self.skeleton.n_joints, 3), -1, dtype=np.intp)
        start = 0
        for j, names in enumerate(self.channels):
            axes = [n[0] for n in names if n.endswith("rotation")]
            order = "".join(axes) + "".join(a for a in "XYZ" if a not in axes)
            cols = {n: start + k for k, n in enumerate(names)}
            joints, columns = groups.setdefault(order, ([], []))
            joints.append(j)
            columns.append([cols.get(f"{a}rotation", -1) for a in order])
            positions[j] = [cols.get(f"{a}position", -1) for a in "XYZ"]
            start += len(names)
        return ({o: (np.array(j, np.intp), np.array(c, np.intp)) for o, (j, c) in groups.items()}, positions)

    def _padded_motion(self) -> Array:
        # A trailing zero column lets column index -1 stand for a missing channel.
        return np.concatenate([self.motion, np.zeros((self.n_frames, 1))], axis=1)

    def _joint_positions(self) -> Array:
        """Constant position-channel values ``(J, 3)`` of non-root joints (0 where absent); root row is 0."""
        _, positions = self._columns()
        values = self._padded_motion()[:, positions[1:]]  # (F, J-1, 3)
        varying = np.any(values != values[:1], axis=(0, 2))
        if np.any(varying):
            name = self.skeleton.names[1 + int(np.flatnonzero(varying)[0])]
            raise BvhError(f"{self.source}: joint {name!r} has animated position channels; only the root may "
                           f"translate")
        out = np.zeros((self.skeleton.n_joints, 3))
        if self.n_frames:
            out[1:] = values[0]
        # Tools that key every joint's translation (MotionBuilder, the Bandai Namco dataset) write the OFFSET again
        # as the channel value: that is the bone, not a translation on top of it.
        has = positions[1:] >= 0
        same = np.all(~has | (np.abs(out[1:] - self.skeleton.offsets[1:]) <= OFFSET_MATCH * np.maximum(
            np.abs(self.skeleton.offsets[1:]), 1.0)), axis=1) & np.any(has, axis=1)
        out[1:][same] = 0.0
        return out

    def posed_skeleton(self) -> Skeleton:
        """The skeleton with constant non-root position channels added to the offsets (for FK of poses).

        Channels whose constant values equal the joint's OFFSET (to :data:`OFFSET_MATCH`) restate the bone and
        add nothing."""
        s = self.skeleton
        return Skeleton(s.names, s.parents, s.offsets + self._joint_positions(), s.rest_rotations)

    def pose_arrays(self) -> tuple[Array, Array]:
        """Local rotations ``(F, J, 4)`` (w, x, y, z) and root translation ``(F, 3)`` in file units.

        Missing rotation axes count as 0 degrees, missing root position axes as 0.  Raises :class:`BvhError`
        if a non-root joint's position channels vary (use :meth:`posed_skeleton` for constant ones).
        """
        self._joint_positions()  # raises if a non-root joint's positions vary
        groups, positions = self._columns()
        padded = self._padded_motion()
        rotations = np.empty((self.n_frames, self.skeleton.n_joints, 4))
        for order, (joints, columns) in groups.items():
            rotations[:, joints] = quat_from_euler(np.radians(padded[:, columns]), order)
        return rotations, padded[:, positions[0]]

    def with_poses(self, rotations: ArrayLike, root_translation: ArrayLike) -> Bvh:
        """A new Bvh with this hierarchy and channels whose motion encodes the given poses.

        ``rotations``: ``(F, J, 4)`` local unit quaternions; ``root_translation``: ``(F, 3)`` in file units.
        Each joint's rotation is decomposed in its channel order (degrees); non-root position channels keep
        their constant values.  Raises :class:`BvhError` where a pose needs an axis the joint has no channel
        for.
        """
        rot = np.asarray(rotations, dtype=np.float64)
        trans = np.asarray(root_translation, dtype=np.float64)
        n_joints = self.skeleton.n_joints
        if rot.ndim != 3 or rot.shape[1:] != (n_joints, 4) or trans.shape != (rot.shape[0], 3):
            raise ValueError(f"expected rotations (F, {n_joints}, 4) and root translation (F, 3), got "
                             f"{rot.shape} and {trans.shape}")
        groups, positions = self._columns()
        n_frames = rot.shape[0]
        # Writes for missing channels (column -1) land in a spare last column, dropped at the end.
        padded = np.zeros((n_frames, self.motion.shape[1] + 1))
        self._joint_positions()  # raises if a non-root joint's positions vary
        if self.n_frames:  # constant non-root position channels are written back as they were
            padded[:, positions[1:]] = self._padded_motion()[0, positions[1:]]
        padded[:, positions[0]] = trans
        if np.any(np.abs(trans[:, positions[0] < 0]) > 1e-9):
            raise BvhError(f"{self.source}: root {self.skeleton.names[0]!r} lacks a position channel for an "
                           f"axis along which the pose translates it")
        for order, (joints, columns) in groups.items():
            angles = euler_from_quat(rot[:, joints], order)  # (F, G, 3) radians
            # Missing axes come last in ``order``, where the decomposition puts 0 even at gimbal lock.
            bad = np.any((np.abs(angles) > 1e-9) & (columns < 0), axis=0)  # (G, 3)
            if np.any(bad):
                g, k = np.argwhere(bad)[0]
                raise BvhError(f"{self.source}: joint {self.skeleton.names[joints[g]]!r} has no "
                               f"{order[k]}rotation channel, but the pose rotates it about {order[k]}")
            padded[:, columns] = np.degrees(angles)
        return Bvh(self.skeleton, self.channels, dict(self.end_sites), self.frame_time, padded[:, :-1],
                   self.source)


def _parse_offset(lines: _Lines, where: str) -> Array:
    number, line, tokens = lines.next(f"'OFFSET x y z' {where}")
    values = [_to_float(t) for t in tokens[1:]]
    if tokens[0] != "OFFSET" or len(values) != 3 or None in values:
        raise lines.error(number, "'OFFSET x y z'", line)
    return np.array(values, dtype=np.float64)


def _parse_channels(lines: _Lines, joint: str) -> tuple[str, ...]:
    number, line, tokens = lines.next(f"'CHANNELS <count> <names>' in joint {joint!r}")
    if tokens[0] != "CHANNELS" or len(tokens) < 2 or not re.fullmatch(r"[0-6]", tokens[1]):
        raise lines.error(number, "'CHANNELS <count 0..6> <names>'", line)
    names = tuple(tokens[2:])
    if len(names) != int(tokens[1]):
        raise _fail(lines.source, number, f"CHANNELS declares {tokens[1]} channels but lists {len(names)}")
    for name in names:
        if name not in CHANNEL_NAMES:
            raise _fail(lines.source, number, f"unknown channel {name!r}, expected one of "
                                              f"{', '.join(CHANNEL_NAMES)}")
        if names.count(name) > 1:
            raise _fail(lines.source, number, f"channel {name!r} listed twice")
    return names


def _expect(lines: _Lines, token: str, what: str) -> None:
    number, line, tokens = lines.next(f"{token!r} {what}")
    if tokens != [token]:
        raise lines.error(number, f"{token!r} {what}", line)


def _parse_hierarchy(lines: _Lines) -> tuple[list[str], list[int], list[Array], list[tuple[str, ...]],
                                             dict[int, Array]]:
    """The ``HIERARCHY`` section: joint names, parents, offsets ``(3,)``, channel names and End Site offsets."""
    source = lines.source
    _expect(lines, "HIERARCHY", "at the start")
    names: list[str] = []
    parents: list[int] = []
    offsets: list[Array] = []
    channels: list[tuple[str, ...]] = []
    end_sites: dict[int, Array] = {}
    defined: dict[str, int] = {}
    stack: list[int] = []  # joints whose closing '}' is pending

    def add_joint(keyword: str, number: int, line: str) -> None:
        # Checks the 'ROOT name' / 'JOINT name' line and reads the joint's '{', OFFSET and CHANNELS lines.
        tokens = line.split(None, 1)
        if tokens[0] != keyword or len(tokens) < 2:
            raise lines.error(number, f"'{keyword} <name>'", line)
        name = tokens[1]
        if name in defined:
            raise _fail(source, number, f"joint name {name!r} already used on line {defined[name]}")
        if len(names) >= MAX_JOINTS:
            raise _fail(source, number, f"more than {MAX_JOINTS} joints")
        defined[name] = number
        _expect(lines, "{", f"after {keyword} {name!r}")
        offsets.append(_parse_offset(lines, f"in joint {name!r}"))
        channels.append(_parse_channels(lines, name))
        parents.append(stack[-1] if stack else -1)
        names.append(name)
        stack.append(len(names) - 1)

    add_joint("ROOT", *lines.next("'ROOT <name>'")[:2])
    while stack:
        joint = names[stack[-1]]
        number, line, tokens = lines.next(f"'}}' closing joint {joint!r}")
        if tokens[0] == "JOINT":
            add_joint("JOINT", number, line)
        elif tokens[:2] == ["End", "Site"]:
            if stack[-1] in end_sites:
                raise _fail(source, number, f"joint {joint!r} has a second End Site")
            _expect(lines, "{", f"after End Site of joint {joint!r}")
            end_sites[stack[-1]] = _parse_offset(lines, f"in End Site of joint {joint!r}")
            _expect(lines, "}", f"closing End Site of joint {joint!r}")
        elif tokens == ["}"]:
            stack.pop()
        else:
            raise lines.error(number, f"'JOINT', 'End Site' or '}}' in joint {joint!r}", line)
    return names, parents, offsets, channels, end_sites


def _parse_motion_header(lines: _Lines, n_joints: int, max_frame_joints: int) -> tuple[int, float, str]:
    """``(frames, seconds per frame, 'declared on line N')`` from the ``MOTION``, ``Frames:`` and ``Frame Time:``
    lines; the size limits are checked here, before any frame is read."""
    source = lines.source
    number, line, tokens = lines.next("'MOTION' after the hierarchy")
    if tokens != ["MOTION"]:
        raise lines.error(number, "'MOTION' after the hierarchy", line)
    number, line, tokens = lines.next("'Frames: <count>'")
    if tokens[0] != "Frames:" or len(tokens) != 2 or not re.fullmatch(r"[0-9]+", tokens[1]):
        raise lines.error(number, "'Frames: <count>'", line)
    n_frames, declared = int(tokens[1]), f"declared on line {number}"
    if n_frames > MAX_FRAMES:
        raise _fail(source, number, f"{n_frames} frames declared; at most {MAX_FRAMES} are supported")
    if n_frames * n_joints > max_frame_joints:
        raise _fail(source, number, f"{n_frames} frames of {n_joints} joints ({n_frames * n_joints} frame-joints) "
                                    f"are more than the {max_frame_joints} allowed here")
    number, line, tokens = lines.next("'Frame Time: <seconds>'")
    frame_time = _to_float(tokens[2]) if tokens[:2] == ["Frame", "Time:"] and len(tokens) == 3 else None
    if frame_time is None or frame_time <= 0:
        raise lines.error(number, "'Frame Time: <seconds>' with seconds > 0", line)
    return n_frames, frame_time, declared


def _parse_frames(lines: _Lines, n_frames: int, n_channels: int, declared: str) -> Array:
    """The remaining lines as ``(n_frames, n_channels)`` channel values; ``declared`` says where the count was."""
    source = lines.source
    rows: list[list[float]] = []
    for number, line in lines.items[lines.pos:]:
        if len(rows) == n_frames:
            raise _fail(source, number, f"more frame lines than the {n_frames} {declared}")
        tokens = line.split()
        if len(tokens) != n_channels:
            raise _fail(source, number, f"frame {len(rows)} has {len(tokens)} values, expected {n_channels}")
        values = [_to_float(t) for t in tokens]
        if None in values:
            k = values.index(None)
            raise _fail(source, number, f"value {k + 1} {tokens[k]!r} is not a number")
        rows.append(values)  # type: ignore[arg-type]
        lines.last = number
    if len(rows) < n_frames and n_channels:
        raise _fail_eof(source, lines.last, f"expected {n_frames} frames as {declared}, found {len(rows)}")
    return np.array(rows, dtype=np.float64).reshape(n_frames, n_channels)


def parse_bvh(text: str, source: str = "<string>", max_frame_joints: int = MAX_FRAME_JOINTS) -> Bvh:
    """Parse BVH text; ``source`` names it in :class:`BvhError` messages.

    One frame per line; messages count frames from 0 and the values of a frame from 1.  A file declaring more
    than ``max_frame_joints`` frames × joints fails at its ``Frames:`` line, before any frame is read.
    """
    lines = _Lines(text, source)
    names, parents, offsets, channels, end_sites = _parse_hierarchy(lines)
    n_frames, frame_time, declared = _parse_motion_header(lines, len(names), max_frame_joints)
    motion = _parse_frames(lines, n_frames, sum(len(c) for c in channels), declared)
    skeleton = Skeleton(names, parents, np.array(offsets))
    return Bvh(skeleton, tuple(channels), end_sites, frame_time, motion, source)


def read_bvh(path: str | os.PathLike[str], max_frame_joints: int = MAX_FRAME_JOINTS) -> Bvh:
    """Read a ``.bvh`` or gzip-compressed ``.bvh.gz`` file; errors name the file (``max_frame_joints``: see
    :func:`parse_bvh`)."""
    path = Path(path)
    data = path.read_bytes()
    if path.suffix == ".gz":
        data = gzip.decompress(data)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = data.decode("latin-1")  # BVH is ASCII in practice; joint names are the only place this matters
    return parse_bvh(text, path.name, max_frame_joints)


def _number(x: float) -> str:
    # Shortest repr that round-trips exactly; "12.0" is written as "12".
    s = repr(x)
    return s[:-2] if s.endswith(".0") else s


def format_bvh(bvh: Bvh) -> str:
    """BVH text (tabs, LF) that :func:`parse_bvh` reads back bit-identically.

    Joints must be in depth-first order (as read from a file); an End Site is written after its joint's
    children.
    """
    if not np.all(np.isfinite(bvh.motion)):
        raise ValueError("motion contains non-finite values, which BVH cannot hold")
    s = bvh.skeleton
    out = ["HIERARCHY"]
    stack: list[int] = []

    def close() -> None:
        j = stack.pop()
        tabs = "\t" * (len(stack) + 1)
        if j in bvh.end_sites:
            out.extend([f"{tabs}End Site", f"{tabs}{{",
                        f"{tabs}\tOFFSET {' '.join(map(_number, bvh.end_sites[j].tolist()))}", f"{tabs}}}"])
        out.append("\t" * len(stack) + "}")

    for j, name in enumerate(s.names):
        while stack and stack[-1] != s.parents[j]:
            close()
        if j and not stack:
            raise ValueError(f"joint {name!r} does not follow its parent's subtree: joints must be in "
                             f"depth-first order to be written as BVH")
        tabs = "\t" * len(stack)
        out.extend([f"{tabs}{'JOINT' if j else 'ROOT'} {name}", f"{tabs}{{",
                    f"{tabs}\tOFFSET {' '.join(map(_number, s.offsets[j].tolist()))}",
                    f"{tabs}\tCHANNELS {len(bvh.channels[j])} {' '.join(bvh.channels[j])}".rstrip()])
        stack.append(j)
    while stack:
        close()
    out.extend(["MOTION", f"Frames: {bvh.n_frames}", f"Frame Time: {float(bvh.frame_time)!r}"])
    out.extend(" ".join(map(_number, row)) for row in bvh.motion.tolist())
    return "\n".join(out) + "\n"


def write_bvh(bvh: Bvh, path: str | os.PathLike[str]) -> None:
    """Write :func:`format_bvh` text to ``path``, gzip-compressed if it ends with ``.gz``.

    The text is written to a temporary name and renamed, so a failure leaves no half-written file.
    """
    path = Path(path)
    data = format_bvh(bvh).encode("utf-8")
    tmp = path.with_name(path.name + ".part")
    try:
        tmp.write_bytes(gzip.compress(data, mtime=0) if path.suffix == ".gz" else data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def bvh_from_poses(skeleton: Skeleton, rotations: ArrayLike, root_translation: ArrayLike, frame_time: float,
                   end_sites: dict[int, Array] | None = None, source: str = "<poses>") -> Bvh:
    """A Bvh holding the given poses of ``skeleton`` (identity rest rotations, as every BVH skeleton has).

    ``rotations``: ``(F, J, 4)`` local (w, x, y, z); ``root_translation``: ``(F, 3)``.  The root gets the channels
    ``Xposition Yposition Zposition Zrotation Yrotation Xrotation``, every other joint ``Zrotation Yrotation
    Xrotation`` (the CMU layout), so any rotation can be written.
    """
    if not np.allclose(skeleton.rest_rotations, [1.0, 0.0, 0.0, 0.0]):
        raise ValueError("BVH skeletons have identity rest rotations; remove the rest pose first")
    rot = np.asarray(rotations, dtype=np.float64)
    channels = (("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"),) + \
        (("Zrotation", "Yrotation", "Xrotation"),) * (skeleton.n_joints - 1)
    frame = Bvh(skeleton, channels, dict(end_sites or {}), frame_time,
                np.zeros((rot.shape[0], 3 + 3 * skeleton.n_joints)), source)
    return frame.with_poses(rot, root_translation)


def clip_from_bvh(bvh: Bvh, first_frame: int = 0, last_frame: int | None = None, mode: PlaybackMode = "loop",
                  in_place: bool = False, name: str = "") -> KeyframeClip:
    """Frames ``first_frame..last_frame`` (inclusive; default: to the end) of a BVH file as a keyframe clip.

    CMU files start with a T-pose calibration frame, so their motion starts at ``first_frame=1``.
    """
    rotations, root = bvh.pose_arrays()
    last = bvh.n_frames - 1 if last_frame is None else last_frame
    if not 0 <= first_frame < last <= bvh.n_frames - 1:
        raise ValueError(f"frame range {first_frame}..{last} is outside 0..{bvh.n_frames - 1} "
                         f"or holds fewer than 2 frames")
    frames = slice(first_frame, last + 1)
    times = np.arange(first_frame, last + 1) * bvh.frame_time
    return KeyframeClip(bvh.posed_skeleton(), times, rotations[frames], root[frames], mode, in_place, 1, name)
