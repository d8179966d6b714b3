"""The thesis clip set: CMU motion capture on the MakeHuman character, keyframe and hybrid, with motion metrics.

For each animation of ``clipset.toml`` (walk, run, crouch, idle) the builder

1. reads the BVH file (checksum-verified) and retargets it onto the character (metres, Y up), turned to face +Z;
2. picks what the file does not give: the gait cycle and keys from the feet, the crouch keys from the hip height,
   the idle keys from the sway;
3. makes the **keyframe** clip: the chosen stretch of mocap resampled to ``fps`` keys per second on a grid whose
   length is a whole number of frames (the stretch is time-scaled by under half a frame to fit; a gait cycle also
   gets an even number of frames so its mirrored half-cycle lands on the grid, and it fades in from the mocap's
   next cycle so the loop is C1; a ping-pong clip eases to rest at its turns); the feet are kept planted where the
   source's feet are down (two-bone IK after retargeting);
4. builds the **hybrid** clips (increments 0, 1, 2) from keys of that keyframe clip, with exactly its period;
5. samples every clip on the same grid (one loop, or one forward-and-back period), puts the floor under the
   keyframe clip's planted feet and measures the motion metrics, hybrids against their keyframe clip.

``write_clip_set`` stores ``manifest.json`` plus one ``<clip_id>.npz`` per clip.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from . import assets, contacts, metrics
from .assets import AssetError
from .bvh import BvhError, read_bvh
from .character import Character, RetargetedCharacter, load_character, retarget
from .clip import PLAYBACK_MODES, KeyframeClip, PlaybackMode, Pose, horizontal
from .footplant import plant_feet
from .hybrid import HybridClip, build_crouch, build_gait, build_idle
from .quat import quat_from_axis_angle, quat_mul, rotate, slerp
from .skeleton import Skeleton

Array = NDArray[np.float64]
Kind = Literal["gait", "crouch", "idle"]

DEFAULT_CONFIG = Path(__file__).with_name("clipset.toml")
ANIMATIONS = ("walk", "run", "crouch", "idle")
FEET = (("LeftFoot", "LeftToeBase"), ("RightFoot", "RightToeBase"))  # each foot: ankle and toe joints
UP = 1
FLOOR_PERCENTILE = 10  # the floor goes under the feet in the lowest 10 % of frames: planted, not mid-stride
MANIFEST = "manifest.json"
LEGS = (("LeftUpLeg", "LeftLeg", "LeftFoot"), ("RightUpLeg", "RightLeg", "RightFoot"))  # IK chains, as FEET
METRES_PER_CMU_UNIT = 0.056444  # the source measured on its own skeleton
LOOP_BLEND_S = 0.2  # a gait loop fades in from the mocap's next cycle over this long (seam C1)
TURN_EASE_S = 0.2  # a ping-pong keyframe clip slows to rest over this long at each turn (no bounce)
CROUCH_START = 0.02  # the crouch starts where the hips have gone 2 % of its depth down
MAX_LAG_FRAMES = {"gait": 2, "crouch": 1, "idle": 1}  # a hybrid further out of phase gets a warning


class ConfigError(ValueError):
    """The clip set configuration is invalid; the message names the file and the entry."""


@dataclass(frozen=True)
class AnimationConfig:
    name: str
    kind: Kind
    source: str
    frames: tuple[int, int]
    playback: PlaybackMode
    in_place: bool
    keys: tuple[int, ...] | None = None
    cycle: tuple[int, int] | None = None


@dataclass(frozen=True)
class ClipSetConfig:
    fps: int
    increments: tuple[int, ...]
    relocate: tuple[str, ...]
    animations: dict[str, AnimationConfig]
    extra_conditions: bool = False  # issue 16's conditions (anim_core/extra_conditions.py) beside the hybrids


def _frames(value: Any, where: str, count: int | None = None) -> tuple[int, ...]:
    if (not isinstance(value, list) or not all(isinstance(v, int) and v >= 0 for v in value)
            or (count is not None and len(value) != count) or list(value) != sorted(set(value))):
        n = f"{count} " if count else ""
        raise ConfigError(f"{where} must be a list of {n}increasing frame numbers, got {value!r}")
    return tuple(value)


def load_config(path: Path = DEFAULT_CONFIG) -> ClipSetConfig:
    """Read and validate the clip set file."""
    try:
        raw = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"clip set file {path} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    fps = raw.get("fps", 30)
    if not isinstance(fps, int) or not 1 <= fps <= 240:
        raise ConfigError(f"{path}: fps must be a whole number of frames per second (1..240), got {fps!r}")
    increments = raw.get("increments", [0, 1, 2])
    if not isinstance(increments, list) or not all(isinstance(i, int) and 0 <= i <= 4 for i in increments):
        raise ConfigError(f"{path}: increments must be a list of integers 0..4, got {increments!r}")
    relocate = raw.get("character", {}).get("relocate", [])
    animations: dict[str, AnimationConfig] = {}
    table = raw.get("animations", {})
    for name in table:
        if name not in ANIMATIONS:
            raise ConfigError(f"{path}: unknown animation {name!r}; the clip set has {', '.join(ANIMATIONS)}")
    for name in ANIMATIONS:
        where = f"{path} [animations.{name}]"
        entry = table.get(name)
        if not isinstance(entry, dict):
            raise ConfigError(f"{where} is missing")
        kind = entry.get("kind")
        if kind not in ("gait", "crouch", "idle"):
            raise ConfigError(f"{where}: kind must be 'gait', 'crouch' or 'idle', got {kind!r}")
        if not isinstance(entry.get("source"), str):
            raise ConfigError(f"{where}: source must name a BVH file in the data directory")
        playback = entry.get("playback", "loop" if kind == "gait" else "pingpong")
        if playback not in PLAYBACK_MODES[:2]:
            raise ConfigError(f"{where}: playback must be 'loop' or 'pingpong', got {playback!r}")
        if (kind == "gait") != (playback == "loop"):
            raise ConfigError(f"{where}: a {kind} plays {'loop' if kind == 'gait' else 'pingpong'} in the hybrid "
                              f"method, so its keyframe clip must too")
        in_place = entry.get("in_place", kind == "gait")
        if not isinstance(in_place, bool):
            raise ConfigError(f"{where}: in_place must be true or false")
        keys = entry.get("keys")
        cycle = entry.get("cycle")
        if cycle is not None and kind != "gait":
            raise ConfigError(f"{where}: only a gait has a cycle")
        animations[name] = AnimationConfig(
            name, kind, entry["source"], _frames(entry.get("frames"), f"{where} frames", 2), playback, in_place,
            None if keys is None else _frames(keys, f"{where} keys", 2),
            None if cycle is None else _frames(cycle, f"{where} cycle", 2))  # type: ignore[arg-type]
    extra = raw.get("extra_conditions", False)
    if not isinstance(extra, bool):
        raise ConfigError(f"{path}: extra_conditions must be true or false, got {extra!r}")
    return ClipSetConfig(fps, tuple(increments), tuple(relocate), animations, extra)


# --- sources ---------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Source:
    """One animation's mocap on the character: a travelling clip at the file's frame rate, facing +Z."""

    config: AnimationConfig
    character: RetargetedCharacter
    clip: KeyframeClip  # times from 0 at config.frames[0]; mode "clamp" (it is only sampled inside)
    frame_time: float
    mocap: Skeleton  # the file's own skeleton (CMU units), on which the clip's rotations play unchanged

    def time_of(self, frame: int) -> float:
        return (frame - self.config.frames[0]) * self.frame_time

    def positions(self, times: Array) -> Array:
        _, pos = self.character.skeleton.forward_kinematics(*self.clip.sample(times, method="slerp"))
        return pos

    def mocap_feet(self, times: Array) -> Array:
        """``(T, 2, 2, 3)`` ankle and toe positions in metres of the mocap on its own skeleton (not retargeted)."""
        rot, root = self.clip.sample(times, method="slerp")
        _, pos = self.mocap.forward_kinematics(rot, root / self.character.root_scale)
        return pos[:, np.array([self.mocap.indices(f) for f in FEET])] * METRES_PER_CMU_UNIT


def _turn(pose: Pose, yaw: float) -> Pose:
    """Rotate whole poses about the vertical axis through the origin."""
    q = quat_from_axis_angle([0.0, 1.0, 0.0], yaw)
    rot = np.array(pose.rotations)
    rot[:, 0] = quat_mul(q, rot[:, 0])
    return Pose(rot, rotate(q, pose.root_translation))


def load_source(data_dir: Path, character: Character, config: AnimationConfig, relocate: tuple[str, ...]) -> Source:
    """Read, retarget and turn one animation's source file (errors name the file)."""
    path = assets.verify(data_dir, config.source)
    try:
        bvh = read_bvh(path)
        rotations, root = bvh.pose_arrays()
    except BvhError as exc:
        raise AssetError(f"corrupt motion file: {exc}") from None
    first, last = config.frames
    if last >= bvh.n_frames:
        raise ConfigError(f"[animations.{config.name}] frames {first}..{last} exceed {path.name}'s "
                          f"{bvh.n_frames} frames")
    rc = retarget(character, bvh.skeleton, bvh.end_sites, relocate=relocate)
    pose = rc.pose(Pose(rotations[first:last + 1], root[first:last + 1]))
    times = np.arange(last - first + 1) * bvh.frame_time
    # Face +Z: a gait along its direction of travel, anything else along the direction the hips face.
    _, pos = rc.skeleton.forward_kinematics(*pose)
    if config.kind == "gait":
        forward = pos[-1, 0] - pos[0, 0]
    else:
        left = pos[:, rc.skeleton.index("LeftUpLeg")] - pos[:, rc.skeleton.index("RightUpLeg")]
        forward = np.cross(left, [0.0, 1.0, 0.0]).mean(axis=0)
    pose = _turn(pose, -float(np.arctan2(forward[0], forward[2])))
    clip = KeyframeClip(rc.skeleton, times, pose.rotations, pose.root_translation, mode="clamp", name=config.name)
    return Source(config, rc, clip, bvh.frame_time, bvh.posed_skeleton())


# --- key picking -----------------------------------------------------------------------------------------------

def _local_maxima(x: Array) -> NDArray[np.intp]:
    """Indices of local maxima, including the first sample when the sequence falls from it (a clip may start
    right at a peak: the run does)."""
    inner = np.flatnonzero((x[1:-1] >= x[:-2]) & (x[1:-1] > x[2:])) + 1
    return np.concatenate([[0], inner]) if x[0] > x[1] else inner


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
    first = source.config.frames[0]
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

@dataclass(frozen=True, eq=False)
class BuiltClip:
    """One clip of the set, sampled on its grid, with its metrics."""

    id: str
    animation: str
    method: Literal["keyframe", "hybrid"]
    increment: int | None
    clip: KeyframeClip | HybridClip
    key_times: Array
    key_rotations: Array
    fps: int
    n_frames: int
    playback: PlaybackMode
    in_place: bool
    root_speed_mps: float
    source: dict[str, Any]
    character: RetargetedCharacter
    local_rotations: Array = field(repr=False)
    root_positions: Array = field(repr=False)
    world_rotations: Array = field(repr=False)
    world_positions: Array = field(repr=False)
    metrics: dict[str, float | None] = field(default_factory=dict)
    condition_id: str | None = None  # set by builders of other conditions (anim_core/extra_conditions.py)

    @property
    def times(self) -> Array:
        return np.arange(self.n_frames) / self.fps

    @property
    def duration_s(self) -> float:
        return self.n_frames / self.fps

    @property
    def condition(self) -> str:
        """The condition id the study server finds this clip by (with its animation)."""
        if self.condition_id is not None:
            return self.condition_id
        return "keyframe" if self.method == "keyframe" else f"hybrid{self.increment}"

    def manifest_entry(self) -> dict[str, Any]:
        return {
            "id": self.id, "animation": self.animation, "method": self.method, "increment": self.increment,
            "key_count": int(self.key_times.size), "duration_s": self.duration_s, "fps": self.fps,
            "frames": self.n_frames, "playback": self.playback, "in_place": self.in_place,
            "root_speed_mps": self.root_speed_mps, "metrics": self.metrics, "source": self.source,
            "file": f"{self.id}.npz", "condition": self.condition,
        }

    def arrays(self) -> dict[str, Array]:
        sk = self.character.skeleton
        return {
            "joint_names": np.array(sk.names), "parents": sk.parents, "offsets": sk.offsets,
            "bind_rotations": self.character.bind_rotations, "bind_positions": self.character.bind_positions,
            "times": self.times, "local_rotations": self.local_rotations, "root_positions": self.root_positions,
            "world_rotations": self.world_rotations, "world_positions": self.world_positions,
            "key_times": self.key_times, "key_rotations": self.key_rotations,
        }


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
        w = 1.0 - _smoothstep(grid[fade] / blend)
    elif src_t[0] - period >= -1e-9:
        fade, shift = grid > clip.duration - blend, -period  # the last keys turn into the previous cycle's
        w = _smoothstep((grid[fade] - (clip.duration - blend)) / blend)
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


def _smoothstep(x: Array) -> Array:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _planted(source: Source, clip: KeyframeClip, src_t: Array) -> KeyframeClip:
    """``clip`` with its feet held where they are while the source's feet are down (:mod:`anim_core.footplant`).

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
                     periodic=loop, ground_velocity=velocity, up_axis=UP)
    if loop:
        rot = np.concatenate([rot, rot[:1]])
    return KeyframeClip(sk, clip.times, rot, clip.root_translation, clip.mode, clip.in_place, clip.up_axis,
                        clip.name)


def _source_skate(source: Source, start: float, stop: float, fps: int) -> float:
    """Foot skate ratio (:mod:`anim_core.contacts`) of the mocap on its own skeleton from ``start`` to ``stop``
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


def build_animation(source: Source, fps: int, increments: tuple[int, ...],
                    progress: Callable[[str], None] = lambda _msg: None) -> list[BuiltClip]:
    """The keyframe clip and the hybrid increments of one animation, sampled and measured."""
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
        key_grid = [_on_grid(t(k), start, stop, keyframe) for k in keys]
        hybrids = [build_gait(keyframe, key_grid, keyframe.duration, increment=i, in_place=cfg.in_place,
                              name=cfg.name) for i in increments]
        keyframe = KeyframeClip(keyframe.skeleton, keyframe.times, keyframe.rotations, keyframe.root_translation,
                                "loop", cfg.in_place, UP, cfg.name)
        source_info = {"file": cfg.source, "cycle_frames": list(cycle), "key_frames": list(keys)}
    elif cfg.kind == "crouch":
        # One stand -> deepest segment played forward and back: both clips are deepest at the turn.
        keys = cfg.keys or pick_crouch(source)
        start, stop = t(keys[0]), t(keys[1])
        keyframe, src_t = _grid_clip(source, start, stop, fps, even=False, mode="pingpong", ease=TURN_EASE_S)
        keyframe = _planted(source, keyframe, src_t)
        hybrids = [build_crouch(keyframe, [0.0, keyframe.duration], increment=i, duration=keyframe.duration,
                                time_scale=None, name=cfg.name) for i in increments]
        source_info = {"file": cfg.source, "frames": [int(keys[0]), int(keys[1])], "key_frames": list(keys)}
    else:
        keys = cfg.keys or pick_idle(source)
        start, stop = t(keys[0]), t(keys[1])
        keyframe, src_t = _grid_clip(source, start, stop, fps, even=False, mode="pingpong", ease=TURN_EASE_S)
        keyframe = _planted(source, keyframe, src_t)
        hybrids = [build_idle(keyframe, [0.0, keyframe.duration], increment=i, name=cfg.name) for i in increments]
        source_info = {"file": cfg.source, "frames": [int(keys[0]), int(keys[1])], "key_frames": list(keys)}
    source_skate = _source_skate(source, t(cfg.frames[0]), t(cfg.frames[1]), fps)

    n_frames = keyframe.n_keys - 1 if cfg.playback == "loop" else 2 * (keyframe.n_keys - 1)
    speed = float(np.linalg.norm(keyframe.velocity)) if cfg.in_place else 0.0
    clips = [(f"{cfg.name}-keyframe", "keyframe", None, keyframe,
              keyframe.times[:-1] if cfg.playback == "loop" else keyframe.times, keyframe.rotations)]
    for i, h in zip(increments, hybrids, strict=True):
        clips.append((f"{cfg.name}-hybrid{i}", "hybrid", i, h, np.asarray(h.key_times), h.key_rotations))

    built: list[BuiltClip] = []
    for clip_id, method, inc, clip, key_times, key_rot in clips:
        progress(f"  {clip_id}: {len(key_times)} keys")
        pose = clip.sample(np.arange(n_frames) / fps)
        built.append(BuiltClip(clip_id, cfg.name, method, inc, clip, np.asarray(key_times, np.float64),
                               np.asarray(key_rot[: len(key_times)]), fps, n_frames, cfg.playback, cfg.in_place,
                               speed, source_info, source.character, pose.rotations, pose.root_translation,
                               *source.character.skeleton.forward_kinematics(*pose)))
    return _measure(_place_on_floor(built), keyframe.velocity if cfg.in_place else np.zeros(3), cfg.kind,
                    source_skate)


def _feet(clip: BuiltClip) -> tuple[NDArray[np.intp], Array]:
    """Foot joint indices ``(2, 2)`` and their flat-standing heights above the soles."""
    idx = np.array([clip.character.skeleton.indices(foot) for foot in FEET])
    return idx, clip.character.contact_heights[idx]


def _place_on_floor(clips: list[BuiltClip]) -> list[BuiltClip]:
    """Shift every clip of an animation by the same amount so the keyframe clip's planted feet are at y = 0 and
    its root is centred horizontally."""
    keyframe = clips[0]
    feet, contact = _feet(keyframe)
    clearance = (keyframe.world_positions[:, feet, UP] - contact).min(axis=(1, 2))
    shift = np.zeros(3)
    shift[UP] = -np.percentile(clearance, FLOOR_PERCENTILE)
    shift[[0, 2]] = -keyframe.root_positions[:, [0, 2]].mean(axis=0)
    return [BuiltClip(**{**c.__dict__, "root_positions": c.root_positions + shift,
                         "world_positions": c.world_positions + shift}) for c in clips]


def _knee_flexion(clip: BuiltClip) -> Array:
    """``(T, 2)`` bend of each knee in radians (0 = straight leg), from the joint positions."""
    legs = np.array([clip.character.skeleton.indices(leg) for leg in LEGS])
    p = clip.world_positions
    thigh = p[:, legs[:, 1]] - p[:, legs[:, 0]]
    shin = p[:, legs[:, 2]] - p[:, legs[:, 1]]
    return np.arctan2(np.linalg.norm(np.cross(thigh, shin), axis=-1), np.sum(thigh * shin, axis=-1))


def _measure(clips: list[BuiltClip], ground_velocity: Array, kind: Kind, source_skate: float) -> list[BuiltClip]:
    """Fill in each clip's metrics; hybrids are compared with the keyframe clip (the first) frame by frame."""
    keyframe = clips[0]
    feet, contact = _feet(keyframe)
    for c in clips:
        m: dict[str, float | None] = {**metrics.foot_metrics(c.world_positions[:, feet], contact, c.fps,
                                                             periodic=True, ground_velocity=ground_velocity)}
        # The skate of issue 14: standing heights from the clip itself, as for the source on its own skeleton.
        m["foot_skate_ratio"] = contacts.foot_skate_ratio(c.world_positions[:, feet], c.fps, UP, periodic=True,
                                                          ground_velocity=ground_velocity)
        m["source_foot_skate_ratio"] = source_skate
        m["mpjpe_mm"] = (None if c.method == "keyframe"
                         else metrics.mpjpe_mm(c.world_positions, keyframe.world_positions))
        m["key_velocity_jump_rad_s"] = metrics.angular_velocity_jumps(lambda t, c=c: c.clip.sample(t).rotations,
                                                                      c.key_times)
        m["jerk_mean"] = metrics.jerk_mean(c.world_positions, c.fps, periodic=True)
        m["bytes"] = metrics.storage_bytes(c.key_times.size, c.character.skeleton.n_joints)
        steps = metrics.frame_steps_mm(c.world_positions)
        m["seam_jump_mm"] = float(steps[-1])
        m["median_step_mm"] = float(np.median(steps[:-1]))
        for name in ("phase_hips_r", "phase_hips_lag", "phase_knee_r", "phase_knee_lag"):
            m[name] = None
        if c.method == "hybrid":
            # A gait's hips bob twice per cycle: a lag of half a cycle would look in phase.
            m["phase_hips_r"], m["phase_hips_lag"] = metrics.phase_alignment(
                keyframe.world_positions[:, 0, UP], c.world_positions[:, 0, UP],
                max_lag=c.n_frames // 4 if kind == "gait" else None)
            m["phase_knee_r"], m["phase_knee_lag"] = metrics.phase_alignment(_knee_flexion(keyframe),
                                                                             _knee_flexion(c))
        c.metrics.update(m)
    return clips


def clip_warnings(clips: list[BuiltClip], config: ClipSetConfig | None = None) -> list[str]:
    """What makes a side-by-side comparison show more than the method: a hybrid out of phase with its keyframe
    clip (best lag beyond :data:`MAX_LAG_FRAMES`) or a seam that jumps (more than twice the median step + 5 mm)."""
    config = config or load_config()
    out = []
    for c in clips:
        m = c.metrics
        limit = 2.0 * m["median_step_mm"] + 5.0
        if m["seam_jump_mm"] > limit:
            out.append(f"{c.id}: the seam jumps {m['seam_jump_mm']:.1f} mm (limit {limit:.1f} mm: twice the "
                       f"median step {m['median_step_mm']:.1f} mm + 5 mm)")
        if c.method == "hybrid":
            allowed = MAX_LAG_FRAMES[config.animations[c.animation].kind]
            for part in ("hips", "knee"):
                lag = m[f"phase_{part}_lag"]
                if abs(lag) > allowed:
                    out.append(f"{c.id}: out of phase with {c.animation}-keyframe: {part} best lag {lag:+d} frames "
                               f"(allowed ±{allowed}), r = {m[f'phase_{part}_r']:.2f} at lag 0")
    return out


# --- the whole set ---------------------------------------------------------------------------------------------

def build_clip_set(data_dir: Path, config: ClipSetConfig | None = None,
                   progress: Callable[[str], None] = lambda _msg: None) -> list[BuiltClip]:
    """All clips of the set (4 animations x (keyframe + increments)), in manifest order."""
    config = config or load_config()
    assets.check_data_dir(data_dir)
    progress("loading the character")
    character = load_character(data_dir)
    clips: list[BuiltClip] = []
    for k, name in enumerate(ANIMATIONS, 1):
        cfg = config.animations[name]
        progress(f"[{k}/{len(ANIMATIONS)}] {name}: {cfg.source}")
        source = load_source(data_dir, character, cfg, config.relocate)
        built = build_animation(source, config.fps, config.increments, progress)
        clips.extend(built)
        if config.extra_conditions:
            from .extra_conditions import build_extra  # it builds on this module

            progress(f"  {name}: the conditions of issue 16")
            clips.extend(build_extra(built, cfg.kind))
    return clips


def write_clip_set(clips: list[BuiltClip], out: Path) -> Path:
    """Write ``<id>.npz`` per clip and ``manifest.json``; returns the manifest path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for c in clips:
        np.savez_compressed(out / f"{c.id}.npz", **c.arrays())
    manifest = {"version": 1, "units": {"length": "m", "time": "s", "up": "+y", "quaternion": "w,x,y,z"},
                "clips": [c.manifest_entry() for c in clips]}
    path = out / MANIFEST
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)  # readers never see a half-written manifest
    return path
