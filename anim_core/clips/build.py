"""Building a clip set from motion capture: one animation's reference on the frame grid, every condition's clip
from it (:mod:`anim_core.methods.conditions`), the clips sampled, placed on the floor and measured.

For each animation (an :class:`AnimationConfig`, read from the clip-set file by ``server.clipset``) the builder

1. takes the motion, already on the canonical CMU skeleton (any common rig is brought there first by
   :func:`anim_core.rig.normalize.normalize_bvh`), and retargets it onto the character (metres, Y up), turned to
   face +Z (a :class:`~anim_core.clips.entry.Source`); a turning gait (or a traveling ``other`` loop) is
   straightened onto one heading (:func:`source_from_bvh`, :func:`straighten_heading`);
2. picks what the description does not give (:mod:`anim_core.clips.reference`): the gait cycle and keys from the
   feet, the crouch keys from the hip height, the idle keys from the sway; an ``other`` motion (any kind of
   movement) plays its whole frame range and its hybrid keys are picked within its tolerance
   (:func:`anim_core.methods.keypick.pick_keys`);
3. makes the **reference** keyframe clip: the chosen stretch of mocap resampled to ``fps`` keys per second on a
   grid whose length is a whole number of frames (the stretch is time-scaled by under half a frame to fit; a gait
   cycle also gets an even number of frames so its mirrored half-cycle lands on the grid, and it fades in from the
   mocap's next cycle so the loop is C1; a ping-pong clip eases to rest at its turns); the feet are kept planted
   where the source's feet are down (two-bone IK after retargeting)
   (:func:`anim_core.clips.reference.reference_animation`);
4. builds each condition's clip with its registered method from that reference and its base keys, with exactly
   its period;
5. samples every clip on the same grid (one loop, or one forward-and-back period), puts the floor under the
   reference's planted feet and measures the motion metrics, every other condition against the reference.

The metrics are measured by :mod:`anim_core.clips.measure`. Nothing here reads files: the server finds, verifies
and writes them (``server.clipset``, ``server.assets``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d

from ..io.bvh import Bvh
from ..math.clip import KeyframeClip, Pose
from ..math.quat import quat_from_axis_angle, quat_mul, rotate
from ..math.skeleton import Skeleton
from ..methods.conditions import REFERENCE, Condition, get_method
from ..methods.footlock import FootLockedClip
from ..methods.lod import HeldClip, max_influences
from ..rig.character import UP, Character, retarget
from . import fidelity
from .entry import DEFAULT_TOLERANCE_MM, METRES_PER_CMU_UNIT, AnimationConfig, ConfigError, KeyCapError, Source
from .measure import clip_feet, measure
from .record import BuiltClip
from .reference import reference_animation, source_skate
from .sources import PINGPONG_TRAVEL_M, root_travel

Array = NDArray[np.float64]

FLOOR_PERCENTILE = 10  # the floor goes under the feet in the lowest 10 % of frames: planted, not mid-stride
#: A gait take, or a traveling ``other`` loop, whose heading (smoothed over :data:`HEADING_SMOOTH_S`) turns by more
#: than this (degrees, largest minus smallest) is straightened before it is built (:func:`straighten_heading`).  The
#: shipped CMU walk and run turn 3.7 and 4.6 degrees: under it, so they build as they always did.
TURN_LIMIT_DEG = 10.0
HEADING_SMOOTH_S = 0.5  # Gaussian sigma (s): a stride's own hip yaw swing (about 1 Hz) is left in, the turn taken out


# --- sources ---------------------------------------------------------------------------------------------------

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
    (:attr:`anim_core.rig.normalize.Normalized.source_positions`), for the fidelity gate; default: ``bvh``'s (a CMU file
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
    animation, source_info, src_t = reference_animation(source, fps)
    keyframe = animation.reference
    skate = source_skate(source, source.time_of(cfg.frames[0]), source.time_of(cfg.frames[1]), fps)

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
    placed = place_on_floor(built)
    if cfg.playback == "loop" and not cfg.in_place:
        # A loop that travels is measured as an in-place one over ground moving under it, as in_place clips are:
        # one period's world positions wrap back by the period's travel, which playback (travel added each cycle)
        # never shows; measured as they are, every traveling loop "jumped" its whole stride length at the seam.
        shift = keyframe.velocity * (np.arange(n_frames) / fps)[:, None]
        view = measure([replace(c, root_positions=c.root_positions - shift,
                                world_positions=c.world_positions - shift[:, None]) for c in placed],
                       keyframe.velocity, cfg.kind, skate)
        measured = [replace(c, metrics=v.metrics) for c, v in zip(placed, view, strict=True)]
    else:
        measured = measure(placed, keyframe.velocity if cfg.in_place else np.zeros(3), cfg.kind, skate)
    for condition, c in zip(ordered, measured, strict=True):
        stored = condition.stored_bytes(c.clip)
        if stored is not None:
            c.metrics["bytes"] = stored
    gated = _gate(source, measured, src_t)
    if any(c.ladder is not None for c in gated):
        distinct_levels(cfg.name, gated, source.character.mesh.weights)
    return gated


def skin_level(c: BuiltClip, weights: Array) -> int | None:
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
               skin_level(c, weights))
        same = seen.get(key)
        if same is not None and c.ladder is not None:
            what = "the reference" if same.method == REFERENCE else f"condition {same.condition!r}"
            raise ConfigError(f"[[ladders]] id = {c.ladder!r} level {c.level!r} ({c.method}): on animation "
                              f"{animation!r} it makes the same clip as {what}; drop the level")
        seen.setdefault(key, c)


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


def place_on_floor(clips: list[BuiltClip]) -> list[BuiltClip]:
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
