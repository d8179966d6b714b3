"""The reference clip of one animation, from its mocap: the source frames picked as keys for each kind (gait, crouch,
idle; :func:`pick_gait`, :func:`pick_crouch`, :func:`pick_idle`), resampled on the clip's frame grid with seamless
loops and turns, the feet planted (:func:`reference_animation`; kind ``other``: :func:`other_reference`), and how
much the source's own feet skate (:func:`source_skate`).  Stage 2 to 4 of :mod:`anim_core.clips.build`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..math import contacts
from ..math.clip import KeyframeClip, PlaybackMode, horizontal
from ..math.quat import slerp
from ..methods.conditions import Animation
from ..methods.footplant import plant_feet
from ..methods.ik import smoothstep
from ..methods.keypick import pick_keys
from ..rig.character import FEET, LEGS, UP
from . import fidelity
from .entry import ConfigError, KeyCapError, Source
from .sources import PINGPONG_TRAVEL_M, root_travel

Array = NDArray[np.float64]

LOOP_BLEND_S = 0.2  # a gait loop fades in from the mocap's next cycle over this long (seam C1)
TURN_EASE_S = 0.2  # a ping-pong keyframe clip slows to rest over this long at each turn (no bounce)
CROUCH_START = 0.02  # the crouch starts where the hips have gone 2 % of its depth down
#: Foot planting turns no thigh of a reference and bends no knee more or less than its source does by more than
#: this (degrees), half the fidelity gate's limit (:data:`anim_core.clips.fidelity.POSE_LIMIT_DEG`): a foot that
#: still slides as it lands is held only as far as the leg reaches it posed as in the motion (the Bandai Namco run).
PLANT_LEG_TOLERANCE_DEG = 0.5 * fidelity.POSE_LIMIT_DEG


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
    source feet skate least (:func:`source_skate`) is taken, the first on a tie: the reference should be the
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
        return source_skate(source, steps[k] * source.frame_time, steps[k + 1] * source.frame_time, 30)

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


def source_skate(source: Source, start: float, stop: float, fps: int) -> float:
    """Foot skate ratio (:mod:`anim_core.math.contacts`) of the mocap on its own skeleton from ``start`` to ``stop``
    seconds (the configured frames) at ``fps``, velocities by central differences with one frame beyond each end
    (held at the file's ends)."""
    return float(np.mean(source_skating_frames(source, start, stop, fps)))


def source_skating_frames(source: Source, start: float, stop: float, fps: int) -> NDArray[np.bool_]:
    """Per frame of :func:`source_skate`'s span, whether a foot is down and sliding: ``(n,)``."""
    n = int(np.floor((stop - start) * fps + 1e-9))
    feet = source.mocap_feet(start + np.arange(-1, n + 2) / fps)
    down = contacts.foot_down(feet[1:-1], UP)
    fast = contacts.foot_speed(feet, fps, UP)[1:-1] > contacts.SKATE_SPEED_MPS
    return np.any(down & fast, axis=1)


def worst_window(flags: NDArray[np.bool_], length: int) -> float:
    """The largest share of ``flags`` over ``length`` consecutive frames, the span read as a loop (a take in a
    sequence loops): the yardstick for a measure taken over a window of that length."""
    n = flags.size
    if length >= n:
        return float(flags.mean())
    wrapped = np.concatenate([flags, flags[:length - 1]]).astype(np.float64)
    return float(np.convolve(wrapped, np.ones(length), "valid").max() / length)


def _on_grid(t: float, start: float, stop: float, clip: KeyframeClip) -> float:
    """Grid time of source time ``t`` in a clip made by :func:`_grid_clip` from ``start..stop``."""
    return clip.nearest_key_time((t - start) / (stop - start) * clip.duration)


def reference_animation(source: Source, fps: int) -> tuple[Animation, dict[str, Any], Array]:
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
        keyframe, key_grid, source_info, src_t = other_reference(source, fps)
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


def other_reference(source: Source, fps: int) -> tuple[KeyframeClip, tuple[float, ...], dict[str, Any], Array]:
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
