"""Building a clip set from motion capture: one animation's reference on the frame grid, every condition's clip
from it (:mod:`anim_core.methods.conditions`), the clips sampled, placed on the floor and measured.

For each animation (an :class:`AnimationConfig`, read from the clip-set file by ``server.clipset``) the builder

1. takes the motion, already on the canonical CMU skeleton (any common rig is brought there first by
   :func:`anim_core.rig.rigmap.normalize_bvh`), and retargets it onto the character (metres, Y up), turned to face +Z;
   a turning gait (or a traveling ``other`` loop) is straightened onto one heading (:func:`source_from_bvh`,
   :func:`straighten_heading`);
2. picks what the description does not give: the gait cycle and keys from the feet, the crouch keys from the hip
   height, the idle keys from the sway; an ``other`` motion (any kind of movement) plays its whole frame range and
   its hybrid keys are picked within its tolerance (:func:`anim_core.methods.keypick.pick_keys`);
3. makes the **reference** keyframe clip: the chosen stretch of mocap resampled to ``fps`` keys per second on a
   grid whose length is a whole number of frames (the stretch is time-scaled by under half a frame to fit; a gait
   cycle also gets an even number of frames so its mirrored half-cycle lands on the grid, and it fades in from the
   mocap's next cycle so the loop is C1; a ping-pong clip eases to rest at its turns); the feet are kept planted
   where the source's feet are down (two-bone IK after retargeting) (:func:`_reference`);
4. builds each condition's clip with its registered method from that reference and its base keys, with exactly
   its period;
5. samples every clip on the same grid (one loop, or one forward-and-back period), puts the floor under the
   reference's planted feet and measures the motion metrics, every other condition against the reference.

The metrics are measured by :mod:`anim_core.clips.measure`. Nothing here reads files: the server finds, verifies
and writes them (``server.clipset``, ``server.assets``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d

from ..io.bvh import Bvh
from ..math import contacts
from ..math.clip import KeyframeClip, PlaybackMode, Pose, horizontal
from ..math.quat import quat_from_axis_angle, quat_mul, rotate, slerp
from ..math.skeleton import Skeleton
from ..math.skinning import SkinnedMesh
from ..methods.conditions import REFERENCE, Animation, Condition, Kind, get_method
from ..methods.footlock import FootLockedClip
from ..methods.footplant import plant_feet
from ..methods.ik import smoothstep
from ..methods.keypick import pick_keys
from ..methods.lod import HeldClip, max_influences, strongest_influences
from ..rig.character import FEET, LEGS, UP, Character, RetargetedCharacter, retarget
from ..rig.rigmap import UNITS
from . import fidelity
from .measure import clip_feet, measure
from .record import BuiltClip
from .sources import PINGPONG_TRAVEL_M, root_travel

Array = NDArray[np.float64]

FLOOR_PERCENTILE = 10  # the floor goes under the feet in the lowest 10 % of frames: planted, not mid-stride
METRES_PER_CMU_UNIT = UNITS["cmu"][0]  # CMU's BVH unit (1 / 0.45 inch)
LOOP_BLEND_S = 0.2  # a gait loop fades in from the mocap's next cycle over this long (seam C1)
TURN_EASE_S = 0.2  # a ping-pong keyframe clip slows to rest over this long at each turn (no bounce)
CROUCH_START = 0.02  # the crouch starts where the hips have gone 2 % of its depth down
#: Foot planting turns no thigh of a reference and bends no knee more or less than its source does by more than
#: this (degrees), half the fidelity gate's limit (:data:`anim_core.clips.fidelity.POSE_LIMIT_DEG`): a foot that
#: still slides as it lands is held only as far as the leg reaches it posed as in the motion (the Bandai Namco run).
PLANT_LEG_TOLERANCE_DEG = 0.5 * fidelity.POSE_LIMIT_DEG


class ConfigError(ValueError):
    """The clip set configuration is invalid; the message names the file and the entry."""


class KeyCapError(ConfigError):
    """Kind ``other``: ``max_keys`` keys do not reach ``tolerance_mm`` (a larger tolerance may)."""


DEFAULT_TOLERANCE_MM = 20.0  # kind "other": the hybrid through the picked keys stays this close to the reference
DEFAULT_MAX_KEYS = 64  # kind "other": key picking gives up beyond this many keys (clip-set field max_keys)
#: A gait take, or a traveling ``other`` loop, whose heading (smoothed over :data:`HEADING_SMOOTH_S`) turns by more
#: than this (degrees, largest minus smallest) is straightened before it is built (:func:`straighten_heading`).  The
#: shipped CMU walk and run turn 3.7 and 4.6 degrees: under it, so they build as they always did.
TURN_LIMIT_DEG = 10.0
HEADING_SMOOTH_S = 0.5  # Gaussian sigma (s): a stride's own hip yaw swing (about 1 Hz) is left in, the turn taken out


@dataclass(frozen=True)
class AnimationConfig:
    """One animation of a clip set: ``source`` names its motion file (BVH of any common rig, or glTF; for the
    manifest, the caller reads it), ``frames`` the source frames searched (kind ``other``: played), ``keys``/``cycle``
    source frames that override the automatic picks.

    How the caller reads the source: ``animation`` picks a glTF file's animation by name or index (default: the
    first); ``mapping`` names an explicit joint-mapping file, ``units`` (a key of :data:`anim_core.rig.rigmap.UNITS`)
    and
    ``up_axis`` (``"y"``/``"z"``) override the detection (:func:`anim_core.rig.rigmap.normalize_bvh`).  ``tolerance_mm``
    (kind ``other``): the largest joint position error, mm, of the hybrid through the picked keys against the
    reference; ``max_keys`` (kind ``other``): the most keys the picking may take to reach it.
    ``accept_unfaithful``: build even if the fidelity gate (:mod:`anim_core.clips.fidelity`) fails; the clips are
    marked as such."""

    name: str
    kind: Kind
    source: str
    frames: tuple[int, int]
    playback: PlaybackMode
    in_place: bool
    keys: tuple[int, ...] | None = None
    cycle: tuple[int, int] | None = None
    tolerance_mm: float = DEFAULT_TOLERANCE_MM
    animation: str | int | None = None
    mapping: str | None = None
    units: str | None = None
    up_axis: Literal["y", "z"] | None = None
    accept_unfaithful: bool = False
    max_keys: int = DEFAULT_MAX_KEYS


# --- sources ---------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Source:
    """One animation's mocap on the character: a travelling clip at the file's frame rate, facing +Z."""

    config: AnimationConfig
    character: RetargetedCharacter
    clip: KeyframeClip  # times from 0 at config.frames[0]; mode "clamp" (it is only sampled inside)
    frame_time: float
    mocap: Skeleton  # the file's own (canonical) skeleton, on which the clip's rotations play unchanged
    metres_per_unit: float = METRES_PER_CMU_UNIT  # of the mocap skeleton
    #: ``(F, 31, 3)`` the canonical joints by the source file's own forward kinematics at config.frames (any units
    #: and orientation: the fidelity gate compares angles)
    own_positions: Array | None = field(default=None, repr=False)
    #: degrees of heading turn taken out of a turning take, first to last frame (:func:`straighten_heading`);
    #: None: the take was not straightened
    straightened_deg: float | None = None

    def time_of(self, frame: int) -> float:
        return (frame - self.config.frames[0]) * self.frame_time

    def positions(self, times: Array) -> Array:
        _, pos = self.character.skeleton.forward_kinematics(*self.clip.sample(times, method="slerp"))
        return pos

    def mocap_feet(self, times: Array) -> Array:
        """``(T, 2, 2, 3)`` ankle and toe positions in metres of the mocap on its own skeleton (not retargeted)."""
        rot, root = self.clip.sample(times, method="slerp")
        _, pos = self.mocap.forward_kinematics(rot, root / self.character.root_scale)
        return pos[:, np.array([self.mocap.indices(f) for f in FEET])] * self.metres_per_unit


def _turn(pose: Pose, yaw: float) -> Pose:
    """Rotate whole poses about the vertical axis through the origin."""
    q = quat_from_axis_angle([0.0, 1.0, 0.0], yaw)
    rot = np.array(pose.rotations)
    rot[:, 0] = quat_mul(q, rot[:, 0])
    return Pose(rot, rotate(q, pose.root_translation))


def heading(positions: Array, skeleton: Skeleton) -> Array:
    """``(T,)`` unwrapped heading (rad) of poses with joint positions ``(T, J, 3)`` (Y up): the direction the hips
    face, ``(right hip -> left hip) x up``, as ``atan2(x, z)`` (0 = facing +Z, positive turning left towards +X)."""
    left = positions[:, skeleton.index("LeftUpLeg")] - positions[:, skeleton.index("RightUpLeg")]
    forward = np.cross(left, [0.0, 1.0, 0.0])
    return np.unwrap(np.arctan2(forward[:, 0], forward[:, 2]))


def _smoothed(x: Array, sigma: float) -> Array:
    """``x (T,)`` smoothed by a Gaussian of ``sigma`` samples, extended at each end by its point reflection about
    the end value, so a steady trend (a steady turn) keeps its slope to the ends instead of flattening there."""
    pad = min(len(x) - 1, int(np.ceil(4.0 * sigma)))
    if pad < 1:
        return np.array(x, dtype=np.float64)
    ext = np.concatenate([2.0 * x[0] - x[pad:0:-1], x, 2.0 * x[-1] - x[-2:-pad - 2:-1]])
    return gaussian_filter1d(ext, sigma, mode="nearest")[pad:pad + len(x)]


def straighten_heading(pose: Pose, skeleton: Skeleton, frame_time: float,
                       smooth_s: float = HEADING_SMOOTH_S) -> tuple[Pose, Array]:
    """A turning take ``pose`` (rotations ``(T, J, 4)``, root ``(T, 3)``, Y up, one frame per ``frame_time`` s)
    walked straight: its progressive turn taken out, each frame turned about the vertical through its root.

    The turn is the hips' heading (:func:`heading`) smoothed by a Gaussian of ``smooth_s`` seconds (the take's
    ends extended by point reflection, so a steady turn is taken out to the last frame), relative to the first
    frame: the swing of the hips within a stride stays, the walk's change of direction goes.  Each frame's
    root rotation is turned back by it, and each step of the root's path by the mean of its two frames' turns (the
    path unrolled; heights unchanged), so the take walks on in the heading of its first frame.  Returns the
    straightened pose and the turn taken out, ``(T,)`` rad.  A foot planted while the body turned slides under it
    by ``turn rate x its distance from the root`` (0.08 m/s for 16 degrees/s at 0.3 m); the reference's foot
    planting holds it again.
    """
    _, pos = skeleton.forward_kinematics(*pose)
    psi = heading(pos, skeleton)
    turn = _smoothed(psi, smooth_s / frame_time) - psi[0]
    rot = np.array(pose.rotations)
    back = quat_from_axis_angle([0.0, 1.0, 0.0], -turn)  # (T, 4)
    rot[:, 0] = quat_mul(back, rot[:, 0])
    root = np.asarray(pose.root_translation, dtype=np.float64)
    steps = rotate(quat_from_axis_angle([0.0, 1.0, 0.0], -0.5 * (turn[1:] + turn[:-1])), np.diff(root, axis=0))
    return Pose(rot, np.concatenate([root[:1], root[:1] + np.cumsum(steps, axis=0)])), turn


def source_from_bvh(bvh: Bvh, character: Character, config: AnimationConfig, relocate: tuple[str, ...],
                    metres_per_unit: float = METRES_PER_CMU_UNIT, source_positions: Array | None = None) -> Source:
    """One animation's mocap (``bvh`` on the canonical CMU skeleton, Y up, ``metres_per_unit``; read from
    ``config.source``) retargeted onto ``character`` and turned to face +Z (errors name the file and the entry).
    A gait take, or a looping ``other`` take that travels (more than :data:`PINGPONG_TRAVEL_M`), whose heading turns
    by more than :data:`TURN_LIMIT_DEG` is first straightened (:func:`straighten_heading`): a loop has one
    direction (closing a turning loop would unwind the turn while the path still curves: the body walked
    sideways and backwards).

    ``source_positions``: ``(F, 31, 3)`` the canonical joints by the source file's own forward kinematics
    (:attr:`anim_core.rig.rigmap.Normalized.source_positions`), for the fidelity gate; default: ``bvh``'s (a CMU file
    is its own source)."""
    rotations, root = bvh.pose_arrays()
    first, last = config.frames
    if last >= bvh.n_frames:
        raise ConfigError(f"[animations.{config.name}] frames {first}..{last} exceed {config.source}'s "
                          f"{bvh.n_frames} frames")
    rc = retarget(character, bvh.skeleton, bvh.end_sites, relocate=relocate, motion=rotations[first:last + 1])
    pose = rc.pose(Pose(rotations[first:last + 1], root[first:last + 1]))
    times = np.arange(last - first + 1) * bvh.frame_time
    straightened = None
    travels = root_travel(root[first:last + 1]) * metres_per_unit > PINGPONG_TRAVEL_M
    if len(times) > 1 and (config.kind == "gait" or (config.kind == "other" and config.playback == "loop" and travels)):
        turned, turn = straighten_heading(pose, rc.skeleton, bvh.frame_time)
        if np.degrees(np.ptp(turn)) > TURN_LIMIT_DEG:
            pose, straightened = turned, float(np.degrees(turn[-1]))
    # Face +Z: a gait along its direction of travel, anything else along the direction the hips face.
    _, pos = rc.skeleton.forward_kinematics(*pose)
    if config.kind == "gait":
        forward = pos[-1, 0] - pos[0, 0]
    else:
        left = pos[:, rc.skeleton.index("LeftUpLeg")] - pos[:, rc.skeleton.index("RightUpLeg")]
        forward = np.cross(left, [0.0, 1.0, 0.0]).mean(axis=0)
    pose = _turn(pose, -float(np.arctan2(forward[0], forward[2])))
    clip = KeyframeClip(rc.skeleton, times, pose.rotations, pose.root_translation, mode="clamp", name=config.name)
    if source_positions is None:
        source_positions = bvh.posed_skeleton().forward_kinematics(rotations, root)[1]
    return Source(config, rc, clip, bvh.frame_time, bvh.posed_skeleton(), metres_per_unit,
                  np.asarray(source_positions)[first:last + 1], straightened)


# --- key picking -----------------------------------------------------------------------------------------------

def _local_maxima(x: Array) -> NDArray[np.intp]:
    """Indices of local maxima, including the first sample when the sequence falls from it (a clip may start
    right at a peak: the run does)."""
    inner = np.flatnonzero((x[1:-1] >= x[:-2]) & (x[1:-1] > x[2:])) + 1
    return np.concatenate([[0], inner]) if x[0] > x[1] else inner


#: A take whose last pose is within this (metres, every joint relative to the hips) of its first is one whole cycle.
LOOP_POSE_M = 0.05


def _loops(positions: Array) -> bool:
    """Is the take ``(T, J, 3)`` one whole cycle: its last pose (relative to the hips) its first again?"""
    if len(positions) < 8:
        return False
    rel = positions - positions[:, :1]
    return float(np.linalg.norm(rel[-1] - rel[0], axis=-1).max()) <= LOOP_POSE_M


def pick_gait(source: Source) -> tuple[int, int, int]:
    """(cycle start = left foot forward at full extension, left foot passing, cycle end) as source frames.

    The left foot is at full forward extension where it leads the right foot by the most (a local maximum, at
    least half the largest lead); a cycle runs to the next such maximum; passing is the first frame after it at
    which the right foot has swung level with the planted left foot.  Of several whole cycles the one whose
    source feet skate least (:func:`_source_skate`) is taken, the first on a tie: the reference should be the
    cleanest stretch of the mocap.
    """
    sk = source.character.skeleton
    pos = source.positions(source.clip.times)
    lead = (pos[:, sk.index("LeftFoot")] - pos[:, sk.index("RightFoot")])[:, 2]
    peaks = [int(p) for p in _local_maxima(lead) if lead[p] > 0.5 * lead.max()]
    # Mocap wobbles: a peak within 0.3 s of a higher one is the same step.
    fps = 1.0 / source.frame_time
    steps = [p for p in peaks if all(lead[p] >= lead[q] for q in peaks if abs(q - p) < 0.3 * fps)]
    name = source.config.name
    first = source.config.frames[0]
    if len(steps) < 2 and _loops(pos):
        # A take of exactly one cycle (its last pose is its first again, as the Bandai Namco runs are cut): the
        # cycle is the whole take, wherever in the stride it was cut.  Its second key is the first passing (the
        # lead changes sign) or full extension (the feet furthest apart: a peak of the lead's size, at least half
        # its largest, as for the steps above) after its first frame, whichever comes first; not the very next
        # frame: a take cut just before a passing (the Bandai run) would put the keys one frame apart, too close
        # for the hybrid's increments.
        size = np.abs(lead)
        events = [k for k in range(2, len(lead) - 1)
                  if (lead[k - 1] > 0.0) != (lead[k] > 0.0)
                  or (size[k] >= size[k - 1] and size[k] > size[k + 1] and size[k] >= 0.5 * size.max())]
        if events:
            return first, first + events[0], first + len(lead) - 1
    if len(steps) < 2:
        raise ConfigError(f"[animations.{name}]: no whole gait cycle found in frames {source.config.frames}; "
                          f"give 'cycle' and 'keys' in the clip set file")
    def skate(k: int) -> float:
        return _source_skate(source, steps[k] * source.frame_time, steps[k + 1] * source.frame_time, 30)

    k = min(range(len(steps) - 1), key=lambda k: (skate(k), k)) if len(steps) > 2 else 0
    start, end = steps[k], steps[k + 1]
    crossing = np.flatnonzero(lead[start:end] <= 0.0)
    if crossing.size == 0:
        raise ConfigError(f"[animations.{name}]: the feet never pass each other in the cycle; give 'keys'")
    return start + first, start + int(crossing[0]) + first, end + first


def pick_crouch(source: Source) -> tuple[int, int]:
    """(standing, deepest crouch) as source frames: the deepest is the lowest hips; standing is the last frame
    before it at which the hips are still within :data:`CROUCH_START` of the crouch's depth of their starting
    height — where the descent begins (mocap often stands still first, and the spring moves from its first
    frame)."""
    hips = source.positions(source.clip.times)[:, 0, UP]
    deepest = int(np.argmin(hips))
    depth = hips[0] - hips[deepest]
    if deepest == 0 or depth <= 0:
        raise ConfigError(f"[animations.{source.config.name}]: the hips never go down; give 'keys'")
    still = np.flatnonzero(hips[:deepest] >= hips[0] - CROUCH_START * depth)
    first = source.config.frames[0]
    return int(still[-1]) + first, deepest + first


def pick_idle(source: Source) -> tuple[int, int]:
    """The two extremes of the sway (hips along their main horizontal direction of motion), in time order."""
    pos = source.positions(source.clip.times)[:, 0, [0, 2]]
    centred = pos - pos.mean(axis=0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    along = centred @ axis
    first = source.config.frames[0]
    a, b = sorted((int(np.argmin(along)), int(np.argmax(along))))
    if a == b:
        raise ConfigError(f"[animations.{source.config.name}]: the hips do not sway; give 'keys'")
    return a + first, b + first


# --- clips -----------------------------------------------------------------------------------------------------

def _grid_times(start: float, stop: float, fps: int, even: bool, ease: float) -> Array:
    """Source times of the keys of :func:`_grid_clip`: a whole (or even) number of frames spanning ``start..stop``
    plus ``ease`` seconds, over which the clip's speed eases from 0 to 1 at the start and back at the end
    (smoothstep speed, so each ramp covers ``ease / 2`` of source time)."""
    span = stop - start
    step = 2 if even else 1
    n = max(2, round((span + ease) * fps / step)) * step
    tau = (span + ease) * np.arange(n + 1) / n
    if ease <= 0:
        return start + tau

    def ramp(x: Array) -> Array:  # integral of smoothstep over [0, x], x in [0, 1]
        return x**3 - 0.5 * x**4

    warped = np.where(tau < ease, ease * ramp(np.clip(tau / ease, 0, 1)),
                      np.where(tau > span, span - ease * ramp(np.clip((span + ease - tau) / ease, 0, 1)),
                               tau - 0.5 * ease))
    return start + warped


def _grid_clip(source: Source, start: float, stop: float, fps: int, even: bool, mode: PlaybackMode,
               ease: float = 0.0) -> tuple[KeyframeClip, Array]:
    """The source between ``start`` and ``stop`` seconds resampled to ``fps`` keys per second, time-scaled to a
    whole (or even) number of frames, optionally easing in and out (:func:`_grid_times`); and the source times
    of its keys."""
    src_t = _grid_times(start, stop, fps, even, ease)
    pose = source.clip.sample(src_t, method="slerp")
    clip = KeyframeClip(source.character.skeleton, np.arange(src_t.size) / fps, pose.rotations,
                        pose.root_translation, mode=mode, name=source.config.name)
    return clip, src_t


def _crossfaded_loop(source: Source, clip: KeyframeClip, src_t: Array, blend: float) -> KeyframeClip:
    """A gait cycle's keys with a seam continuous in pose *and* velocity: over the first ``blend`` seconds the
    keys fade (smoothstep, slerp) in from the mocap one cycle later — the poses that really follow the cycle's
    end — so the loop's first key is the pose after its last, and the fade starts and ends with zero slope.
    Where the file has no cycle after this one, the last ``blend`` seconds fade towards the cycle before; with
    neither, the pose mismatch is spread over the cycle (:meth:`KeyframeClip.closed_loop`)."""
    period = float(src_t[-1] - src_t[0])
    grid = clip.times
    if src_t[0] + period + blend <= source.clip.duration + 1e-9:
        fade, shift = grid < blend, period  # the next cycle's poses come first
        w = 1.0 - smoothstep(grid[fade] / blend)
    elif src_t[0] - period >= -1e-9:
        fade, shift = grid > clip.duration - blend, -period  # the last keys turn into the previous cycle's
        w = smoothstep((grid[fade] - (clip.duration - blend)) / blend)
    else:
        return clip.closed_loop()
    other = source.clip.sample(src_t[fade] + shift, method="slerp")
    travel = horizontal(source.clip.sample(np.array([src_t[0] + shift])).root_translation[0]
                        - source.clip.sample(np.array([src_t[0]])).root_translation[0], UP)
    rot = np.array(clip.rotations)
    rot[fade] = slerp(rot[fade], other.rotations, w[:, None])
    root = np.array(clip.root_translation)
    root[fade] += w[:, None] * (other.root_translation - travel - root[fade])
    if shift > 0:
        rot[-1], root[-1] = rot[0], root[0] + travel  # key n is the pose key 0 faded in from, one cycle on
    else:
        rot[-1], root[-1] = rot[0], root[0] - travel
    return KeyframeClip(clip.skeleton, grid, rot, root, clip.mode, clip.in_place, clip.up_axis, clip.name)


def _planted(source: Source, clip: KeyframeClip, src_t: Array) -> KeyframeClip:
    """``clip`` with its feet held where they are while the source's feet are down (:mod:`anim_core.methods.footplant`).

    Contacts are detected on the mocap on its own skeleton at the keys' source times; a loop is planted as one
    period in place (the ground moving under it), so a phase may run across the seam."""
    sk = clip.skeleton
    legs = [tuple(int(j) for j in sk.indices(leg)) for leg in LEGS]
    loop = clip.mode == "loop"
    keys = slice(0, -1) if loop else slice(None)
    down = contacts.foot_down(source.mocap_feet(src_t[keys]), UP)
    velocity = clip.velocity if loop else np.zeros(3)
    root = clip.root_translation[keys] - velocity * clip.times[keys, None]
    feet = [tuple(int(j) for j in sk.indices(foot)) for foot in FEET]
    rot = plant_feet(sk, clip.rotations[keys], root, legs, down, 1.0 / (clip.times[1] - clip.times[0]), feet,
                     periodic=loop, ground_velocity=velocity, up_axis=UP, max_leg_change_deg=PLANT_LEG_TOLERANCE_DEG)
    if loop:
        rot = np.concatenate([rot, rot[:1]])
    return KeyframeClip(sk, clip.times, rot, clip.root_translation, clip.mode, clip.in_place, clip.up_axis,
                        clip.name)


def _source_skate(source: Source, start: float, stop: float, fps: int) -> float:
    """Foot skate ratio (:mod:`anim_core.math.contacts`) of the mocap on its own skeleton from ``start`` to ``stop``
    seconds (the configured frames) at ``fps``, velocities by central differences with one frame beyond each end
    (held at the file's ends)."""
    n = int(np.floor((stop - start) * fps + 1e-9))
    feet = source.mocap_feet(start + np.arange(-1, n + 2) / fps)
    down = contacts.foot_down(feet[1:-1], UP)
    fast = contacts.foot_speed(feet, fps, UP)[1:-1] > contacts.SKATE_SPEED_MPS
    return float(np.mean(np.any(down & fast, axis=1)))


def _on_grid(t: float, start: float, stop: float, clip: KeyframeClip) -> float:
    """Grid time of source time ``t`` in a clip made by :func:`_grid_clip` from ``start..stop``."""
    return clip.nearest_key_time((t - start) / (stop - start) * clip.duration)


def _reference(source: Source, fps: int) -> tuple[Animation, dict[str, Any], Array]:
    """The reference keyframe clip of one animation on the frame grid, with its base keys, as builders receive it
    (:class:`~anim_core.methods.conditions.Animation`); what the manifest records of the source; and the source
    times (s from ``config.frames[0]``) of the reference's keys."""
    cfg = source.config
    t = source.time_of
    if cfg.kind == "gait":
        picked = pick_gait(source) if cfg.cycle is None or cfg.keys is None else None
        cycle = cfg.cycle or (picked[0], picked[2])
        keys = cfg.keys or picked[:2]
        if keys[0] != cycle[0]:
            raise ConfigError(f"[animations.{cfg.name}]: the gait cycle starts at the first key, but cycle "
                              f"{list(cycle)} and keys {list(keys)} differ")
        start, stop = t(cycle[0]), t(cycle[1])
        keyframe, src_t = _grid_clip(source, start, stop, fps, even=True, mode="loop")
        keyframe = _planted(source, _crossfaded_loop(source, keyframe, src_t, LOOP_BLEND_S), src_t)
        key_grid = tuple(_on_grid(t(k), start, stop, keyframe) for k in keys)
        keyframe = KeyframeClip(keyframe.skeleton, keyframe.times, keyframe.rotations, keyframe.root_translation,
                                "loop", cfg.in_place, UP, cfg.name)
        source_info = {"file": cfg.source, "cycle_frames": list(cycle), "key_frames": list(keys)}
        if source.straightened_deg is not None:
            # What the clips show: the walk on one heading, not the take's turn (recorded, not hidden).
            source_info["straightened_deg"] = round(source.straightened_deg, 1)
    elif cfg.kind == "other":
        keyframe, key_grid, source_info, src_t = _other_reference(source, fps)
    else:
        # crouch: one stand -> deepest segment played forward and back, so reference and hybrid are deepest at the
        # turn; idle: the sway between its two extremes.
        keys = cfg.keys or (pick_crouch(source) if cfg.kind == "crouch" else pick_idle(source))
        start, stop = t(keys[0]), t(keys[1])
        keyframe, src_t = _grid_clip(source, start, stop, fps, even=False, mode="pingpong", ease=TURN_EASE_S)
        keyframe = _planted(source, keyframe, src_t)
        key_grid = (0.0, keyframe.duration)
        source_info = {"file": cfg.source, "frames": [int(keys[0]), int(keys[1])], "key_frames": list(keys)}
    # Mirrored about a bind made from the clip itself, so that the hybrid is the same whatever rig the take came on.
    animation = Animation(cfg.name, cfg.kind, keyframe, key_grid, keyframe.duration, cfg.in_place, fps,
                          source.character.mirror_bind(keyframe.rotations))
    return animation, source_info, src_t


def _other_reference(source: Source, fps: int) -> tuple[KeyframeClip, tuple[float, ...], dict[str, Any], Array]:
    """Kind ``other``: the whole frame range on the grid (a loop closed, :meth:`KeyframeClip.closed_loop`; a
    ping-pong clip easing to rest at its turns), planted; its base keys given (source frames, mapped to the grid)
    or picked on it within ``tolerance_mm`` (:func:`anim_core.methods.keypick.pick_keys`)."""
    cfg = source.config
    loop = cfg.playback == "loop"
    start, stop = source.time_of(cfg.frames[0]), source.time_of(cfg.frames[1])
    keyframe, src_t = _grid_clip(source, start, stop, fps, even=False, mode=cfg.playback,
                                 ease=0.0 if loop else TURN_EASE_S)
    if loop:
        keyframe = keyframe.closed_loop()
    keyframe = _planted(source, keyframe, src_t)
    keyframe = KeyframeClip(keyframe.skeleton, keyframe.times, keyframe.rotations, keyframe.root_translation,
                            cfg.playback, cfg.in_place, UP, cfg.name)
    where = f"[animations.{cfg.name}]"
    if not loop:
        # Played forward and back, a take that travels walks its second half backwards: refused, not built.
        # Measured in the file's own metres, as clips inspect measures it: what it suggests builds.
        travel = root_travel(keyframe.root_translation) / source.character.root_scale * source.metres_per_unit
        if travel > PINGPONG_TRAVEL_M:
            raise ConfigError(f"{where} playback: the root travels {travel:.2f} m (more than {PINGPONG_TRAVEL_M} m); "
                              f"played ping-pong, every second half would move it backwards. Set playback = "
                              f"\"loop\" (the take plays forward and starts again; in_place = true keeps it on the "
                              f"spot)")
    if cfg.keys is not None:
        key_grid = tuple(_on_grid(source.time_of(k), start, stop, keyframe) for k in cfg.keys)
        if len(set(key_grid)) < len(key_grid):
            raise ConfigError(f"{where} keys: {list(cfg.keys)} fall on the same frames of the {fps} fps grid")
        frames = list(cfg.keys)
        picked: dict[str, Any] = {}
    else:
        try:
            keys = pick_keys(keyframe, cfg.tolerance_mm / 1000.0, max_keys=cfg.max_keys, mode=cfg.playback)
        except ValueError as exc:
            raise KeyCapError(f"{where} tolerance_mm: {exc}") from None
        key_grid = keys.times
        frames = [cfg.frames[0] + round(src_t[f] / source.frame_time) for f in keys.frames]
        picked = {"tolerance_mm": cfg.tolerance_mm, "key_error_mm": round(keys.error * 1000.0, 3)}
    source_info = {"file": cfg.source, "frames": list(cfg.frames), "key_frames": frames, **picked}
    if source.straightened_deg is not None:
        source_info["straightened_deg"] = round(source.straightened_deg, 1)
    return keyframe, key_grid, source_info, src_t


def build_animation(source: Source, fps: int, conditions: Sequence[Condition],
                    progress: Callable[[str], None] = lambda _msg: None) -> list[BuiltClip]:
    """One clip per condition of one animation (the reference first), sampled and measured; clip ids are
    ``<animation>-<condition id>``."""
    cfg = source.config
    reference = [c for c in conditions if c.is_reference]
    if len(reference) != 1:
        raise ConfigError(f"the clip set needs exactly one condition with method {REFERENCE!r} (the reference), "
                          f"got {len(reference)}")
    ordered = [*reference, *(c for c in conditions if not c.is_reference)]
    animation, source_info, src_t = _reference(source, fps)
    keyframe = animation.reference
    source_skate = _source_skate(source, source.time_of(cfg.frames[0]), source.time_of(cfg.frames[1]), fps)

    n_frames = keyframe.n_keys - 1 if cfg.playback == "loop" else 2 * (keyframe.n_keys - 1)
    speed = float(np.linalg.norm(keyframe.velocity)) if cfg.in_place else 0.0
    built: list[BuiltClip] = []
    for condition in ordered:
        clip_id = f"{cfg.name}-{condition.id}"
        try:
            clip = condition.build(animation)
        except ValueError as exc:
            raise ConfigError(f"[[conditions]] {condition.id!r} on animation {cfg.name!r}: {exc}") from None
        key_times = np.asarray(clip.key_times, np.float64)
        progress(f"  {clip_id}: {key_times.size} keys")
        pose = clip.sample(np.arange(n_frames) / fps)
        built.append(BuiltClip(clip_id, cfg.name, cfg.kind, condition.id, condition.method,
                               condition.params_dict(), clip, key_times, np.asarray(clip.key_rotations), fps,
                               n_frames, cfg.playback, cfg.in_place, speed, source_info, source.character,
                               pose.rotations, pose.root_translation,
                               *source.character.skeleton.forward_kinematics(*pose), ladder=condition.ladder,
                               level=condition.level, render=condition.render_settings()))
    placed = _place_on_floor(built)
    if cfg.playback == "loop" and not cfg.in_place:
        # A loop that travels is measured as an in-place one over ground moving under it, as in_place clips are:
        # one period's world positions wrap back by the period's travel, which playback (travel added each cycle)
        # never shows; measured as they are, every traveling loop "jumped" its whole stride length at the seam.
        shift = keyframe.velocity * (np.arange(n_frames) / fps)[:, None]
        view = measure([replace(c, root_positions=c.root_positions - shift,
                                world_positions=c.world_positions - shift[:, None]) for c in placed],
                       keyframe.velocity, cfg.kind, source_skate)
        measured = [replace(c, metrics=v.metrics) for c, v in zip(placed, view, strict=True)]
    else:
        measured = measure(placed, keyframe.velocity if cfg.in_place else np.zeros(3), cfg.kind, source_skate)
    for condition, c in zip(ordered, measured, strict=True):
        stored = condition.stored_bytes(c.clip)
        if stored is not None:
            c.metrics["bytes"] = stored
    gated = _gate(source, measured, src_t)
    if any(c.ladder is not None for c in gated):
        distinct_levels(cfg.name, gated, source.character.mesh.weights)
        for c, cost in zip(gated, run_time_costs(gated, source.character.mesh), strict=True):
            c.metrics.update(cost)  # every clip of a clip set with ladders: the levels compare with all of them
    return gated


def _skin_level(c: BuiltClip, weights: Array) -> int | None:
    """The influences per vertex a clip is rendered with, None for the full skin (also when a level keeps every
    weight of the character's skin: at least its most influences per vertex)."""
    k = (c.render or {}).get("skin_influences")
    return None if k is None or k >= max_influences(weights) else int(k)


def distinct_levels(animation: str, clips: Sequence[BuiltClip], weights: Array) -> None:
    """Every level of a ladder makes a clip of its own: a level whose clip has the same frames (local rotations
    and root) and is rendered with the same skin as the reference's or another level's is a ConfigError naming
    the ladder, the level and the clip it repeats."""
    seen: dict[tuple[bytes, bytes, int | None], BuiltClip] = {}
    for c in clips:  # the reference first
        key = (np.ascontiguousarray(c.local_rotations).tobytes(), np.ascontiguousarray(c.root_positions).tobytes(),
               _skin_level(c, weights))
        same = seen.get(key)
        if same is not None and c.ladder is not None:
            what = "the reference" if same.method == REFERENCE else f"condition {same.condition!r}"
            raise ConfigError(f"[[ladders]] id = {c.ladder!r} level {c.level!r} ({c.method}): on animation "
                              f"{animation!r} it makes the same clip as {what}; drop the level")
        seen.setdefault(key, c)


def run_time_costs(clips: Sequence[BuiltClip], mesh: SkinnedMesh) -> list[dict[str, float]]:
    """Each clip's measured run-time cost (:mod:`anim_core.bench.cost`): ``cost_ms_per_1000``, and for the
    reference and each render-time condition ``skin_ms_per_1000`` and ``skin_weights`` (the non-zero skin weights
    of the body it is skinned with: what an engine's per-vertex loop blends); one animation's clips timed
    interleaved."""
    from ..bench.cost import pose_costs_ms_per_1000, skin_costs_ms_per_1000

    out = [{"cost_ms_per_1000": round(ms, 4)} for ms in pose_costs_ms_per_1000([c.clip for c in clips])]
    skinned = [k for k, c in enumerate(clips) if c.render is not None or c.method == REFERENCE]
    levels = [_skin_level(clips[k], mesh.weights) for k in skinned]
    for k, level, ms in zip(skinned, levels, skin_costs_ms_per_1000(clips[0].clip, mesh, levels), strict=True):
        out[k]["skin_ms_per_1000"] = round(ms, 2)
        weights = mesh.weights if level is None else strongest_influences(mesh.joints, mesh.weights, level)[1]
        out[k]["skin_weights"] = int(np.count_nonzero(weights))  # weights blended per character and frame
    return out


#: Kind ``other``: the tolerances (mm) :func:`suggest_tolerance` tries in turn, the default first, and the largest
#: share of the reference's stored bytes the cheapest condition (the hybrid through the picked keys, increment 0)
#: may take for the suggestion to count as cheap.
SUGGESTED_TOLERANCES_MM = (DEFAULT_TOLERANCE_MM, 30.0, 50.0, 80.0, 120.0)
CHEAP_BYTE_RATIO = 0.5


@dataclass(frozen=True)
class ToleranceSuggestion:
    """A ``tolerance_mm`` for kind ``other`` and what building the animation with it gave: the hybrid's (increment
    0) keys and stored bytes against the reference's."""

    tolerance_mm: float
    keys: int
    reference_keys: int
    bytes: int
    reference_bytes: int

    @property
    def key_ratio(self) -> float:
        return self.keys / self.reference_keys

    @property
    def byte_ratio(self) -> float:
        return self.bytes / self.reference_bytes

    @property
    def cheap(self) -> bool:
        return self.byte_ratio <= CHEAP_BYTE_RATIO

    def describe(self) -> str:
        measured = (f"built: the hybrid (increment 0) has {self.keys} of the reference's {self.reference_keys} keys "
                    f"(key ratio {self.key_ratio:.2f}) and stores {self.bytes} of its {self.reference_bytes} bytes "
                    f"(byte ratio {self.byte_ratio:.2f})")
        if self.cheap:
            return f"tolerance_mm = {self.tolerance_mm:g}  ({measured})"
        return (f"tolerance_mm = {self.tolerance_mm:g}  ({measured}; even so the hybrid is not cheap: more than "
                f"{CHEAP_BYTE_RATIO:.0%} of the reference's bytes - the motion has little to leave out; give 'keys')")


def suggest_tolerance(source: Source, fps: int) -> ToleranceSuggestion:
    """The smallest of :data:`SUGGESTED_TOLERANCES_MM` at which the animation ``source`` (kind ``other``, played as
    its config says, with its ``max_keys``) builds a hybrid (increment 0) that stores at most
    :data:`CHEAP_BYTE_RATIO` of the reference's bytes, measured by building the reference and that hybrid (through
    the fidelity gate: :class:`ConfigError` if it fails); the largest that builds if none is cheap
    (:attr:`ToleranceSuggestion.cheap` is false then).  A tolerance that ``max_keys`` keys do not reach is skipped
    (the suggestion must build); :class:`KeyCapError` if none is reached."""
    conditions = (Condition.parse("keyframe", REFERENCE), Condition.parse("hybrid0", "hybrid", {"increment": 0}))
    suggestion = None
    for tolerance in SUGGESTED_TOLERANCES_MM:
        config = replace(source.config, kind="other", tolerance_mm=tolerance)
        try:
            reference, hybrid = build_animation(replace(source, config=config), fps, conditions)
        except KeyCapError as exc:
            if tolerance == SUGGESTED_TOLERANCES_MM[-1] and suggestion is None:
                raise KeyCapError(f"{exc} (tried tolerance_mm {', '.join(f'{t:g}' for t in SUGGESTED_TOLERANCES_MM)}"
                                  f"; raise max_keys)") from None
            continue
        suggestion = ToleranceSuggestion(tolerance, int(hybrid.key_times.size), int(reference.key_times.size),
                                         int(hybrid.metrics["bytes"]), int(reference.metrics["bytes"]))
        if suggestion.cheap:
            break
    assert suggestion is not None
    return suggestion


def _source_poses(source: Source, times: Array) -> Array:
    """``(T, 31, 3)`` the source's own forward kinematics at source times (s from ``config.frames[0]``), linear
    between its frames."""
    own = source.own_positions
    assert own is not None
    x = np.clip(np.asarray(times) / source.frame_time, 0.0, own.shape[0] - 1.0)
    i = np.minimum(np.floor(x).astype(np.intp), own.shape[0] - 2) if own.shape[0] > 1 else np.zeros(x.shape, np.intp)
    w = (x - i)[:, None, None]
    return own[i] * (1.0 - w) + own[np.minimum(i + 1, own.shape[0] - 1)] * w


def _gate(source: Source, clips: list[BuiltClip], src_t: Array) -> list[BuiltClip]:
    """The fidelity gate (:mod:`anim_core.clips.fidelity`) on one animation's built clips (the reference first): the
    figures go into each clip's metrics; a failure raises :class:`ConfigError` naming the animation or condition,
    the check, the bone and the frame, unless ``accept_unfaithful`` (then the clips are marked)."""
    cfg = source.config
    reference = clips[0]
    n = src_t.size - 1  # the reference's keys span n frames of the grid
    k = np.arange(reference.n_frames)
    times = src_t[np.where(k <= n, k, 2 * n - k)] if cfg.playback == "pingpong" else src_t[np.minimum(k, n)]
    candidates = [_source_poses(source, times)]
    slack, bone_slack = None, 0.0
    if cfg.playback == "loop":  # the seam fades between this cycle and the next or the previous one
        period = float(src_t[-1] - src_t[0])
        candidates += [_source_poses(source, times + period), _source_poses(source, times - period)]
        # A stretch that does not end as it began is closed by spreading the difference over the loop.
        end_poses = _source_poses(source, src_t[[0, -1]])
        ends = fidelity.pose_angles(end_poses)
        slack = np.degrees(np.abs(ends[1] - ends[0]))
        bone_slack = float(fidelity.bone_angles(end_poses[1:], end_poses[:1])[0])
    contact = reference.character.contact_heights
    source_frames = cfg.frames[0] + np.round(times / source.frame_time).astype(np.intp)
    checks = [fidelity.check_reference(reference.world_positions, contact, candidates, slack, source_frames,
                                       bone_slack)]
    loop = cfg.playback == "loop"
    checks += [fidelity.check_condition(c.world_positions, contact, _gate_reference(c, reference), loop,
                                        _mirrored_half(cfg, c), c.fps) for c in clips[1:]]
    out = []
    for c, check in zip(clips, checks, strict=True):
        if check.problems and not cfg.accept_unfaithful:
            what = "the reference" if c is reference else f"condition {c.condition!r}"
            raise ConfigError(f"[animations.{cfg.name}] ({cfg.source}): {what} fails the fidelity gate: "
                              f"{'; '.join(check.problems)}. Check the source's mapping, units and up axis (clips "
                              f"inspect), or set accept_unfaithful = true to build it anyway (marked as unfaithful)")
        # Every clip of an animation whose reference is unfaithful is: the conditions are made from it.
        unfaithful = bool(check.problems or checks[0].problems)
        metrics = {**c.metrics, **check.as_metrics(), "unfaithful": 1.0 if unfaithful else 0.0}
        out.append(replace(c, metrics=metrics, fidelity=check))
    return out


def _gate_reference(c: BuiltClip, reference: BuiltClip) -> Array:
    """What the gate compares a condition's frames with: the reference's frames, or for a held clip
    (``update_rate``, :class:`~anim_core.methods.lod.HeldClip`) the reference's frames held as it holds them.  A
    held clip shows only the reference's own poses (its tests check each frame is the reference's held frame);
    what it loses between two updates, a foot's landing say, is the condition a study measures, not a fault of
    the clip."""
    if isinstance(c.clip, HeldClip):
        return reference.world_positions[c.clip.shown[:c.n_frames]]
    return reference.world_positions


def _mirrored_half(cfg: AnimationConfig, clip: BuiltClip) -> tuple[NDArray[np.intp], int] | None:
    """For a gait condition whose second half cycle mirrors its first (a hybrid's keys and their mirror images,
    :attr:`anim_core.methods.hybrid.SquadClip.mirror`, also under foot locking or the C2 spline): the frames of its
    keyed half's keys and the half's length in frames, for :func:`anim_core.clips.fidelity.check_mirror`."""
    if cfg.kind != "gait" or clip.n_frames % 2 or not get_method(clip.method).mirrors:
        return None
    half = clip.n_frames // 2
    if isinstance(clip.clip, FootLockedClip):  # its legs are posed by IK at the keys too, by design
        return np.zeros(0, np.intp), half
    frames = np.round(np.asarray(clip.key_times) * clip.fps).astype(np.intp)
    return frames[frames < half], half


def _place_on_floor(clips: list[BuiltClip]) -> list[BuiltClip]:
    """Shift every clip of an animation by the same amount so the keyframe clip's planted feet are at y = 0 and
    its root is centred horizontally."""
    keyframe = clips[0]
    feet, contact = clip_feet(keyframe)
    clearance = (keyframe.world_positions[:, feet, UP] - contact).min(axis=(1, 2))
    shift = np.zeros(3)
    shift[UP] = -np.percentile(clearance, FLOOR_PERCENTILE)
    shift[[0, 2]] = -keyframe.root_positions[:, [0, 2]].mean(axis=0)
    return [BuiltClip(**{**c.__dict__, "root_positions": c.root_positions + shift,
                         "world_positions": c.world_positions + shift}) for c in clips]
