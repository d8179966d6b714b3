"""The fidelity gate of a clip-set build: is what participants see the motion the source holds?

Conventions: joint positions ``(T, 31, 3)`` of the canonical (CMU) joints
(:data:`anim_core.rig.rigmap.CANONICAL_NAMES`), Y up, the floor at y = 0 for the built clips; angles in degrees
in results, radians inside.

Two kinds of check (:func:`check_reference`, :func:`check_condition`):

* **Body checks**, on every clip as built (on the floor): *upright* — the head above the hips in every frame
  (``upright_m``: the smallest head-over-hips height); *grounded* — each foot reaches the floor at some frame
  (``foot_reach_m``: the larger of the two feet's lowest clearance) and nothing goes under it (``under_floor_m``:
  the deepest joint below the floor); *handedness* — the character's left hip is on its left (``handedness``:
  the share of frames where the left hip lies on the side that "up x forward" points to, forward being where the
  bent knees point).
* **Pose against the source** (the reference only): angles between bones (:data:`ANGLES`: knees, elbows, thighs
  and upper arms against the spine, the hip line against the shoulder line) of the character against the same
  angles of the source file's own forward kinematics at the same source time (``pose_error_deg``: the largest
  difference, named by angle and frame).  Bone lengths and rest poses differ between rigs; these angles do not.

A condition is compared with its reference instead: a frame whose angles differ from the reference's by more than
:data:`FOLD_DEG`, or whose head goes under its hips where the reference's does not, flips or folds the body.

**Every clip** participants see (issue 35: the reference passed while its hybrids were 58-62 degrees off with a foot
that never landed) is also measured by what a viewer notices (:func:`check_body`):

* *bone directions* (``bone_error_deg``): the 95th percentile over frames of the largest angle between a bone's world
  direction and the same bone's in what the clip is held against (the source for the reference, the reference for a
  condition), each frame turned about up to the body's own facing (twist and stacked joints show, not only flips);
* *widths* (``hip_width_ratio``, ``shoulder_width_ratio``): the hip and shoulder widths relative to the leg length,
  against the source's (reference) or the reference's (condition): outside ``[1 / WIDTH_RATIO, WIDTH_RATIO]`` fails
  (stacked hips: both thighs from one point);
* *knees* (``knees_forward``): the share of frames with a knee bent by more than :data:`KNEE_BENT_DEG` in which it
  bends forward — the shin behind the thigh, ``(thigh x shin) . hip line > 0`` — for the worse knee; under
  :data:`HANDEDNESS_MIN` fails (a backward knee, or left and right swapped);
* *landing* (``landing_m``, conditions): in every contact phase of the reference (a foot down,
  :func:`anim_core.math.contacts.foot_down`), the condition's foot must come within :data:`LANDING_M` of the lowest the
  reference's foot comes there (a foot that never lands fails); ``landing_m`` is the worst phase's excess.

A **composite** (a sequence of takes, a layered take, a blend of two; issue 39) is held against its takes
(:func:`check_composite`): the body checks; widths and knees against its first take; and every frame that shows one
take alone (a sequence's cut everywhere, any transition once its switch has settled) must be a pose of that take,
its bones within :data:`TAKE_POSE_DEG` of the take's nearest frame (``bone_error_deg``; a take played on another
take's skeleton was 9-21 degrees off, and the transition metrics all looked fine).

Handedness is read from the hips and the knees (forward is where the bent knees point), not from the toes: the
toes of a swinging foot point back.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..math import contacts
from ..rig.mirror import mirror_partners
from ..rig.rigmap import CANONICAL_NAMES

Array = NDArray[np.float64]

_I = {n: i for i, n in enumerate(CANONICAL_NAMES)}
#: Angle name -> the two bones (from joint, to joint) whose directions it measures.
ANGLES: dict[str, tuple[tuple[str, str], tuple[str, str]]] = {
    "left knee": (("LeftUpLeg", "LeftLeg"), ("LeftLeg", "LeftFoot")),
    "right knee": (("RightUpLeg", "RightLeg"), ("RightLeg", "RightFoot")),
    "left elbow": (("LeftArm", "LeftForeArm"), ("LeftForeArm", "LeftHand")),
    "right elbow": (("RightArm", "RightForeArm"), ("RightForeArm", "RightHand")),
    "left thigh to spine": (("Spine", "Spine1"), ("LeftUpLeg", "LeftLeg")),
    "right thigh to spine": (("Spine", "Spine1"), ("RightUpLeg", "RightLeg")),
    "left upper arm to spine": (("Spine", "Spine1"), ("LeftArm", "LeftForeArm")),
    "right upper arm to spine": (("Spine", "Spine1"), ("RightArm", "RightForeArm")),
    "hip line to shoulder line": (("RightUpLeg", "LeftUpLeg"), ("RightArm", "LeftArm")),
}
ANGLE_NAMES = tuple(ANGLES)
_A = np.array([[[_I[a], _I[b]] for a, b in bones] for bones in ANGLES.values()])  # (A, 2 bones, 2 joints)
_FEET = np.array([[_I["LeftFoot"], _I["LeftToeBase"]], [_I["RightFoot"], _I["RightToeBase"]]])

#: The reference may differ from the source's own pose angles by this much (degrees): foot planting turns thighs
#: and bends knees (by at most half this, :data:`anim_core.clips.reference.PLANT_LEG_TOLERANCE_DEG`; the shipped
#: references: 0.5..9.0 degrees) and a loop's seam fades between two cycles; a broken retarget (stacked hips, a
#: thigh folded up) is off by 45..90 degrees.
POSE_LIMIT_DEG = 20.0
#: Each foot must come this close to the floor (metres) somewhere in the clip, and no joint may go deeper under it.
FOOT_REACH_M = 0.05
UNDER_FLOOR_M = 0.05
#: The share of frames in which the character's left must be on its left.
HANDEDNESS_MIN = 0.5
#: A condition whose pose angles differ from its reference's by more than this (degrees) in a frame folds the body.
FOLD_DEG = 90.0
#: The reference's world bone directions may differ from the source's by this much (degrees, 95th percentile over
#: frames of the largest bone angle): foot planting and the seam's fade move bones (the shipped CMU references: up to
#: 9 degrees; a broken retarget 45-90).
BONE_LIMIT_DEG = 25.0
#: Hip and shoulder widths (relative to the leg length) may be this many times larger or smaller than what the clip
#: is held against: the character's proportions are its own (MakeHuman's hips are 0.25 leg lengths wide, CMU's
#: subjects' 0.2-0.25), a stacked pair of thighs is 0.
WIDTH_RATIO = 2.0
#: A knee counts as bent (and so tells which way it bends) beyond this angle between thigh and shin (degrees).
KNEE_BENT_DEG = 20.0
#: A gait hybrid's keyed frames must equal the reference's within this (degrees, largest bone angle).
KEY_LIMIT_DEG = 1.0
#: In each stance of its reference a condition's foot must come this close (metres) to where the reference's does.
LANDING_M = 0.03
#: A contact phase of the reference shorter than this (seconds) is a foot brushing the floor, not a step.
STANCE_MIN_S = 0.12
#: A gait hybrid's mirrored half may differ from the reference's other half by as much as its keyed half differs
#: from the reference plus how far the reference's own halves are from mirror images (the subject's asymmetry),
#: plus this (degrees, 95th percentiles).  Mirroring about a rest pose that is a stride (issue 35) overshot it by
#: 20-30 degrees; mirroring about the character's bind pose stays within it on every take measured
#: (docs/motion-from-the-wild.md).
MIRROR_MARGIN_DEG = 5.0
#: ... and its mirrored half must be the mirror image of its keyed half as a viewer sees the body (degrees, 95th
#: percentile of the largest bone angle): exact at the keys; between them SQUAD interpolates twists the mirror gives
#: the mirrored keys, and a foot-locked hybrid's IK targets follow each half's own contacts.
SELF_MIRROR_DEG = 10.0
#: A composite's frame that shows one take alone must be a pose of that take within this (degrees, the largest bone
#: angle to the take's nearest frame): exact by design (the sample sequences: 0.0 in their cuts, at most 1.0 once a
#: transition has settled, the settle measure's 1 degree per joint); the run played on the idle's skeleton was 21 off.
TAKE_POSE_DEG = 2.0
_PARTNER = mirror_partners(CANONICAL_NAMES)

#: Bones whose world directions :func:`bone_directions` compares: (from joint, to joint).
BONES: tuple[tuple[str, str], ...] = (
    ("LeftUpLeg", "LeftLeg"), ("LeftLeg", "LeftFoot"), ("LeftFoot", "LeftToeBase"),
    ("RightUpLeg", "RightLeg"), ("RightLeg", "RightFoot"), ("RightFoot", "RightToeBase"),
    ("Hips", "Spine1"), ("Spine1", "Head"), ("RightUpLeg", "LeftUpLeg"), ("RightArm", "LeftArm"),
    ("LeftArm", "LeftForeArm"), ("LeftForeArm", "LeftHand"), ("RightArm", "RightForeArm"),
    ("RightForeArm", "RightHand"))
_B = np.array([[_I[a], _I[b]] for a, b in BONES])
_LEGS = np.array([[_I[f"{s}UpLeg"], _I[f"{s}Leg"], _I[f"{s}Foot"]] for s in ("Left", "Right")])


def pose_angles(positions: Array) -> Array:
    """``(..., A)`` angles (radians, 0..pi) between the bone pairs of :data:`ANGLES` for positions ``(..., 31, 3)``."""
    p = np.asarray(positions, dtype=np.float64)
    bones = p[..., _A[:, :, 1], :] - p[..., _A[:, :, 0], :]  # (..., A, 2, 3)
    a, b = bones[..., 0, :], bones[..., 1, :]
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def _knees(positions: Array) -> tuple[Array, Array, Array]:
    """Per frame and leg ``(..., 2)``: the knee's bend (radians), whether it bends forward (``(thigh x shin) . hip
    line > 0``: the shin behind the thigh of a body whose left is the left) and where it points ``(..., 2, 3)`` (the
    knee away from the hip-ankle line, horizontal)."""
    p = np.asarray(positions, dtype=np.float64)
    hip, knee, ankle = (p[..., _LEGS[:, k], :] for k in range(3))
    thigh, shin = knee - hip, ankle - knee
    bend = np.arctan2(np.linalg.norm(np.cross(thigh, shin), axis=-1), np.sum(thigh * shin, axis=-1))
    line = (p[..., _I["LeftUpLeg"], :] - p[..., _I["RightUpLeg"], :])[..., None, :]
    forward = np.sum(np.cross(thigh, shin) * line, axis=-1) > 0.0
    points = knee - 0.5 * (hip + ankle)
    points[..., 1] = 0.0
    return bend, forward, points


def handedness(positions: Array) -> Array:
    """``(...)``: +1 where the left hip is on the body's left ("up x forward", forward where the bent knees point),
    -1 where it is on the right, 0 where it cannot be told (no knee bent by :data:`KNEE_BENT_DEG`)."""
    p = np.asarray(positions, dtype=np.float64)
    bend, _, points = _knees(p)
    bent = bend > np.radians(KNEE_BENT_DEG)
    forward = np.sum(points * bent[..., None], axis=-2)
    left_dir = np.cross([0.0, 1.0, 0.0], forward)
    hips = p[..., _I["LeftUpLeg"], :] - p[..., _I["RightUpLeg"], :]
    return np.where(bent.any(axis=-1), np.sign(np.sum(hips * left_dir, axis=-1)), 0.0)


def bone_directions(positions: Array) -> Array:
    """``(T, B, 3)`` unit directions of :data:`BONES` for positions ``(T, 31, 3)``, each frame turned about up so the
    body faces +Z (its facing from the hip line); a bone of zero length gives zeros."""
    p = np.asarray(positions, dtype=np.float64)
    line = p[:, _I["LeftUpLeg"]] - p[:, _I["RightUpLeg"]]
    yaw = np.arctan2(line[:, 2], line[:, 0])  # turning by it brings the hip line (the body's left) onto +X
    c, s = np.cos(yaw), np.sin(yaw)
    v = p[:, _B[:, 1]] - p[:, _B[:, 0]]
    turned = np.stack([c[:, None] * v[..., 0] + s[:, None] * v[..., 2], v[..., 1],
                       -s[:, None] * v[..., 0] + c[:, None] * v[..., 2]], axis=-1)
    norm = np.linalg.norm(turned, axis=-1, keepdims=True)
    return np.divide(turned, norm, out=np.zeros_like(turned), where=norm > 1e-12)


def bone_angles(positions: Array, other: Array) -> Array:
    """``(T,)`` the largest angle (degrees) between a bone of ``positions`` and the same bone of ``other`` per frame
    (both ``(T, 31, 3)``, any units; each turned to its own facing, :func:`bone_directions`); bones of zero length in
    ``other`` (an unmapped joint of a source) are left out."""
    return _largest_angle(bone_directions(positions), bone_directions(other))


def _largest_angle(a: Array, b: Array) -> Array:
    """The largest angle (degrees) between bone directions ``a`` and ``b`` ``(..., B, 3)`` over the bones, leaving
    out the bones of zero length in ``b``."""
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))
    has = np.linalg.norm(b, axis=-1) > 0.5
    return np.where(has, angle, 0.0).max(axis=-1)


def widths(positions: Array) -> tuple[float, float]:
    """Mean hip and shoulder widths (thigh heads, upper arm heads) of ``(T, 31, 3)`` relative to the mean leg length
    (thigh + shin)."""
    p = np.asarray(positions, dtype=np.float64)
    legs = p[:, _LEGS]
    leg = float(np.mean(np.linalg.norm(legs[:, :, 1] - legs[:, :, 0], axis=-1)
                        + np.linalg.norm(legs[:, :, 2] - legs[:, :, 1], axis=-1)))
    hips = float(np.mean(np.linalg.norm(p[:, _I["LeftUpLeg"]] - p[:, _I["RightUpLeg"]], axis=-1)))
    shoulders = float(np.mean(np.linalg.norm(p[:, _I["LeftArm"]] - p[:, _I["RightArm"]], axis=-1)))
    return (hips / leg, shoulders / leg) if leg > 0 else (0.0, 0.0)


@dataclass(frozen=True)
class Fidelity:
    """A clip's fidelity figures (:meth:`as_metrics`) and the problems that fail the gate (empty: it passes)."""

    upright_m: float
    foot_reach_m: float
    under_floor_m: float
    handedness: float
    pose_error_deg: float | None = None
    pose_error_at: str | None = None
    problems: tuple[str, ...] = field(default=())
    bone_error_deg: float | None = None
    hip_width_ratio: float | None = None
    shoulder_width_ratio: float | None = None
    knees_forward: float | None = None
    landing_m: float | None = None
    mirror_error_deg: float | None = None
    against: str | None = None  # what the clip is held against, where it is not the source or the reference

    @property
    def ok(self) -> bool:
        return not self.problems

    def as_metrics(self) -> dict[str, float | None]:
        return {"upright_m": round(self.upright_m, 4), "foot_reach_m": round(self.foot_reach_m, 4),
                "under_floor_m": round(self.under_floor_m, 4), "handedness": round(self.handedness, 3),
                "pose_error_deg": None if self.pose_error_deg is None else round(self.pose_error_deg, 2),
                **{name: None if value is None else round(value, 4) for name, value in (
                    ("bone_error_deg", self.bone_error_deg), ("hip_width_ratio", self.hip_width_ratio),
                    ("shoulder_width_ratio", self.shoulder_width_ratio), ("knees_forward", self.knees_forward),
                    ("landing_m", self.landing_m), ("mirror_error_deg", self.mirror_error_deg))}}

    def summary(self) -> str:
        pose = "" if self.pose_error_deg is None else f", pose {self.pose_error_deg:.1f} deg ({self.pose_error_at})"
        return (f"head over hips >= {self.upright_m:.2f} m, feet reach {self.foot_reach_m * 1000:.0f} mm, "
                f"under floor {self.under_floor_m * 1000:.0f} mm, left on the left {self.handedness:.0%}{pose}")


def _body(positions: Array, contact_heights: Array) -> tuple[float, float, float, float, list[str]]:
    p = positions
    up = p[:, _I["Head"], 1] - p[:, _I["Hips"], 1]
    clearance = p[:, _FEET, 1] - contact_heights[_FEET]  # (T, 2, 2)
    reach = clearance.min(axis=(0, 2))  # per foot
    others = np.setdiff1d(np.arange(p.shape[1]), _FEET.ravel())
    under = min(float(clearance.min()), float(p[:, others, 1].min()))
    hand = handedness(p)
    told = hand != 0
    left_share = float(np.mean(hand[told] > 0)) if told.any() else 1.0
    problems = []
    if up.min() <= 0:
        frame = int(np.argmin(up))
        problems.append(f"upside down: the head is {-up[frame] * 100:.0f} cm below the hips at frame {frame}")
    for side, r in zip(("left", "right"), reach, strict=True):
        if r > FOOT_REACH_M:
            problems.append(f"the {side} foot never comes lower than {r * 100:.0f} cm above the floor (a hovering "
                            f"leg)")
    if under < -UNDER_FLOOR_M:
        frame = int(np.argmin(np.minimum(clearance.min(axis=(1, 2)), p[:, others, 1].min(axis=1))))
        problems.append(f"{-under * 100:.0f} cm under the floor at frame {frame}")
    if left_share < HANDEDNESS_MIN:
        problems.append(f"left and right swapped: the left hip is on the body's right in {1 - left_share:.0%} of "
                        f"the frames (check the mapping of Left/Right joints)")
    return float(up.min()), float(reach.max()), under, left_share, problems


def check_reference(positions: Array, contact_heights: Array, source_positions: Array | list[Array],
                    slack_deg: Array | None = None, source_frames: NDArray[np.intp] | None = None,
                    bone_slack_deg: float = 0.0) -> Fidelity:
    """The gate on a reference clip: body checks on ``positions`` ``(T, 31, 3)`` (metres, on the floor;
    ``contact_heights`` ``(31,)`` the joints' heights above the soles standing) and its pose angles against
    ``source_positions`` ``(T, 31, 3)`` (the source's own forward kinematics at the same source times, any units
    and orientation), or against the closer of several such arrays per frame (a loop's seam fades between two
    cycles).  ``slack_deg`` ``(A,)``: what each angle may differ beyond :data:`POSE_LIMIT_DEG` by design (a loop
    of a stretch that does not end where it began is closed by spreading that difference over it).
    ``source_frames`` ``(T,)``: the source file's frame of each clip frame, named in the messages.
    ``bone_slack_deg``: what the bones may differ beyond :data:`BONE_LIMIT_DEG` by design (the same closing of a loop:
    the largest bone angle between the stretch's first and last pose)."""
    up, reach, under, hand, problems = _body(positions, contact_heights)
    candidates = source_positions if isinstance(source_positions, list) else [source_positions]
    mine = pose_angles(positions)
    diff = np.min([np.abs(mine - pose_angles(s)) for s in candidates], axis=0)  # (T, A)
    slack = np.zeros(len(ANGLES)) if slack_deg is None else np.asarray(slack_deg, dtype=np.float64)
    beyond = np.degrees(diff) - slack
    frame, angle = np.unravel_index(int(np.argmax(beyond)), beyond.shape)
    worst = float(np.degrees(diff[frame, angle]))
    where = f"frame {frame}" + ("" if source_frames is None else f" (source frame {int(source_frames[frame])})")
    at = f"{ANGLE_NAMES[angle]} at {where}"
    if beyond[frame, angle] > POSE_LIMIT_DEG:
        allowed = POSE_LIMIT_DEG + slack[angle]
        problems.append(f"not faithful to the source: the {ANGLE_NAMES[angle]} angle is {worst:.0f} degrees off at "
                        f"clip {where} (limit {allowed:.0f})")
    figures, body = check_body(positions, candidates[0], "source")
    bones = np.min([bone_angles(positions, c) for c in candidates], axis=0)
    figures["bone_error_deg"] = float(np.percentile(bones, 95))
    if figures["bone_error_deg"] > BONE_LIMIT_DEG + bone_slack_deg:
        frame = int(np.argmax(bones))
        where = f"frame {frame}" + ("" if source_frames is None else f" (source frame {int(source_frames[frame])})")
        problems.append(f"not faithful to the source: its bones point {figures['bone_error_deg']:.0f} degrees from the "
                        f"source's (95th percentile; {bones[frame]:.0f} at clip {where}; limit "
                        f"{BONE_LIMIT_DEG + bone_slack_deg:.0f})")
    return Fidelity(up, reach, under, hand, worst, at, tuple(problems + body), **figures)


def check_condition(positions: Array, contact_heights: Array, reference: Array, periodic: bool = False,
                    mirror: tuple[NDArray[np.intp], int] | None = None, fps: float = 30.0) -> Fidelity:
    """The gate on a condition's clip ``(T, 31, 3)`` against its reference on the same frames: it must not flip
    (head under the hips where the reference's is not) or fold (an angle of :data:`ANGLES` more than
    :data:`FOLD_DEG` from the reference's); its widths and knees (:func:`check_body`) and its landing in each of the
    reference's contact phases (:func:`check_landing`; ``periodic``: a loop, whose phases wrap) are gated; its other
    floor figures are reported.  ``mirror``: ``(key frames, half)`` of a gait hybrid whose second half mirrors its
    first (:func:`check_mirror`)."""
    up, reach, under, hand, _ = _body(positions, contact_heights)
    problems = []
    head = positions[:, _I["Head"], 1] - positions[:, _I["Hips"], 1]
    ref_head = reference[:, _I["Head"], 1] - reference[:, _I["Hips"], 1]
    flipped = np.flatnonzero((head <= 0) & (ref_head > 0))
    if flipped.size:
        problems.append(f"flips the body: the head is under the hips at frames {flipped[0]}..{flipped[-1]}")
    diff = np.abs(pose_angles(positions) - pose_angles(reference))
    frame, angle = np.unravel_index(int(np.argmax(diff)), diff.shape)
    worst = float(np.degrees(diff[frame, angle]))
    if worst > FOLD_DEG:
        problems.append(f"folds the body: the {ANGLE_NAMES[angle]} angle is {worst:.0f} degrees from the "
                        f"reference's at frame {frame}")
    figures, body = check_body(positions, reference, "reference")
    landing, unlanded = check_landing(positions, contact_heights, reference, periodic, fps)
    mirrored = None
    if mirror is not None:
        mirrored, unmirrored, _ = check_mirror(positions, reference, *mirror)
        body += unmirrored
    return Fidelity(up, reach, under, hand, worst, f"{ANGLE_NAMES[angle]} at frame {frame}",
                    tuple(problems + body + unlanded), **figures, landing_m=landing, mirror_error_deg=mirrored)


#: Narrower hips than this (leg lengths) are no human's: both thighs start from one point (the hips are stacked, or a
#: mapping took the hip centre for the thigh heads).
STACKED_HIPS = 0.05


def _widths_problems(positions: Array, against: Array, what: str) -> tuple[float, float, list[str]]:
    mine, theirs = widths(positions), widths(against)
    ratios = [m / t if t > 0 else float("inf") for m, t in zip(mine, theirs, strict=True)]
    problems = []
    for side, hips in (("", mine[0]), (f"the {what}'s ", theirs[0])):
        if hips < STACKED_HIPS:
            problems.append(f"{side or 'its '}thighs start from one point (hip width {hips:.2f} leg lengths)"
                            + (": the mapping's LeftUpLeg and RightUpLeg are not the thigh heads; check them (clips "
                               "inspect) or give a mapping file" if side else ": stacked hips"))
    for part, ratio, m, t in zip(("hip", "shoulder"), ratios, mine, theirs, strict=True):
        if not 1.0 / WIDTH_RATIO <= ratio <= WIDTH_RATIO and not (part == "hip" and min(m, t) < STACKED_HIPS):
            problems.append(f"the {part} width is {m:.2f} leg lengths against the {what}'s {t:.2f}")
    return ratios[0], ratios[1], problems


def _knee_shares(positions: Array) -> list[float | None]:
    """Per knee (left, right): the share of its bent frames in which it bends forward, None if never bent."""
    bend, forward, _ = _knees(positions)
    bent = bend > np.radians(KNEE_BENT_DEG)
    return [float(np.mean(forward[bent[:, k], k])) if bent[:, k].any() else None for k in range(2)]


def _knees_problems(positions: Array, against: Array) -> tuple[float | None, list[str]]:
    shares, theirs = _knee_shares(positions), _knee_shares(against)
    told = [x for x in shares if x is not None]
    if not told:
        return None, []
    # Judged against what the clip is held against: a source whose own knees bend "backwards" by this measure (a
    # pose it holds) makes no backward knee of its clip.
    problems = [f"the {side} knee bends backwards in {1 - share:.0%} of the frames it is bent, the "
                f"{'source' if other is None else 'one it is held against'}'s in {1 - (other or 1.0):.0%} (a mapping "
                f"with left and right swapped, or a leg turned about itself)"
                for side, share, other in zip(("left", "right"), shares, theirs, strict=True)
                if share is not None and share < HANDEDNESS_MIN and (other is None or other >= HANDEDNESS_MIN)]
    return min(told), problems


def check_body(positions: Array, against: Array, what: str) -> tuple[dict[str, float | None], list[str]]:
    """What every clip is measured by against ``against`` (the source's positions for a reference, the reference's
    for a condition; ``(T, 31, 3)``, any units): bone directions, widths and knees (see the module docstring).  The
    bone figure is reported, not gated, here: a reference gates it (:data:`BONE_LIMIT_DEG`), a condition by its
    fold (:data:`FOLD_DEG`)."""
    bones = float(np.percentile(bone_angles(positions, against), 95))
    hips, shoulders, problems = _widths_problems(positions, against, what)
    knees, knee_problems = _knees_problems(positions, against)
    return ({"bone_error_deg": bones, "hip_width_ratio": hips, "shoulder_width_ratio": shoulders,
             "knees_forward": knees}, problems + knee_problems)


def take_pose_angles(positions: Array, take: Array) -> Array:
    """``(T,)`` for each frame of ``positions`` ``(T, 31, 3)``, the largest bone angle (degrees, :func:`bone_angles`)
    to the nearest frame of ``take`` ``(G, 31, 3)``: 0 where the frame is one of the take's poses."""
    return _largest_angle(bone_directions(positions)[:, None], bone_directions(take)[None]).min(axis=1)


def check_composite(positions: Array, contact_heights: Array, first: Array,
                    shown: list[tuple[str, NDArray[np.intp], Array]]) -> Fidelity:
    """The gate on a composite's clip ``(T, 31, 3)`` (metres, on the floor): the body checks, its widths and knees
    against ``first`` (its first take or base, ``(G, 31, 3)``, any length), and ``shown``: per take, its name, the
    frames of the clip that show it alone and its own poses ``(G, 31, 3)`` (on its own skeleton), each such frame
    within :data:`TAKE_POSE_DEG` of one of them."""
    up, reach, under, hand, problems = _body(positions, contact_heights)
    hips, shoulders, width_problems = _widths_problems(positions, first, "first take")
    knees, knee_problems = _knees_problems(positions, first)
    worst, at = None, None
    for name, frames, take in shown:
        if frames.size:
            angles = take_pose_angles(positions[frames], take)
            k = int(np.argmax(angles))
            if worst is None or angles[k] > worst:
                worst, at = float(angles[k]), f"{name} at frame {int(frames[k])}"
    if worst is not None and worst > TAKE_POSE_DEG:
        problems.append(f"not its takes: the {at} has its bones {worst:.0f} degrees from the nearest pose of that "
                        f"take (limit {TAKE_POSE_DEG:.0f})")
    return Fidelity(up, reach, under, hand, None, at, tuple(problems + width_problems + knee_problems),
                    bone_error_deg=worst, hip_width_ratio=hips, shoulder_width_ratio=shoulders, knees_forward=knees,
                    against="takes")


def check_landing(positions: Array, contact_heights: Array, reference: Array, periodic: bool, fps: float
                  ) -> tuple[float, list[str]]:
    """Does each foot of a condition ``(T, 31, 3)`` land in every contact phase of its ``reference`` (same frames,
    metres, on the floor; ``contact_heights`` ``(31,)``): come within :data:`LANDING_M` of the lowest the reference's
    foot comes in that phase (and within :data:`FOOT_REACH_M` of the floor would do too)?  The worst phase's excess
    over the reference's lowest (m) and the problems (a foot that never lands).  Phases shorter than
    :data:`STANCE_MIN_S` at ``fps`` frames per second are left out."""
    down = contacts.foot_down(reference[:, _FEET], 1)
    clearance = (positions[:, _FEET, 1] - contact_heights[_FEET]).min(axis=2)  # (T, 2)
    planted = (reference[:, _FEET, 1] - contact_heights[_FEET]).min(axis=2)
    n = len(positions)
    worst, problems = -np.inf, []
    for f, side in enumerate(("left", "right")):
        for start, stop in contacts.contact_intervals(down[:, f], periodic):
            if stop - start < STANCE_MIN_S * fps:
                continue
            frames = np.arange(start, stop) % n
            lowest, theirs = float(clearance[frames, f].min()), float(planted[frames, f].min())
            worst = max(worst, lowest - theirs)
            if lowest > max(theirs + LANDING_M, FOOT_REACH_M):
                problems.append(f"the {side} foot never lands in the reference's contact at frames {start}..{stop - 1}"
                                f" (it stays {lowest * 100:.0f} cm above the floor, the reference's comes down to "
                                f"{theirs * 100:.0f} cm)")
                break
    return (float(worst) if np.isfinite(worst) else 0.0), problems


def check_mirror(positions: Array, reference: Array, key_frames: NDArray[np.intp], half: int
                 ) -> tuple[float, list[str], float]:
    """A gait hybrid ``(T, 31, 3)`` whose frames ``half..`` mirror its first ``half`` frames, against its reference
    (same frames): its keyed frames ``key_frames`` (in the first half) must equal the reference's
    (:data:`KEY_LIMIT_DEG`)
    and its mirrored half must differ from the reference's other half by no more than its keyed half does plus the
    reference's own asymmetry plus :data:`MIRROR_MARGIN_DEG` (95th percentiles of the largest bone angle), and be the
    mirror image of its own keyed half (:data:`SELF_MIRROR_DEG`).  Returns the mirrored half's figure against the
    reference, the problems and the figure against its own keyed half's image."""
    n = 2 * half
    keyed = bone_angles(positions[:half], reference[:half])
    mirrored = bone_angles(positions[half:n], reference[half:n])
    image = reference[:half][:, _PARTNER] * np.array([-1.0, 1.0, 1.0])  # the reference's keyed half, mirrored
    asymmetry = bone_angles(image, reference[half:n])
    own_image = positions[:half][:, _PARTNER] * np.array([-1.0, 1.0, 1.0])
    own = float(np.percentile(bone_angles(positions[half:n], own_image), 95))
    keys = float(keyed[key_frames].max()) if len(key_frames) else 0.0
    p_keyed, p_mirrored, p_asym = (float(np.percentile(x, 95)) for x in (keyed, mirrored, asymmetry))
    problems = []
    if keys > KEY_LIMIT_DEG:
        frame = int(key_frames[int(np.argmax(keyed[key_frames]))])
        problems.append(f"its keyed frame {frame} is {keys:.1f} degrees from the reference's (limit {KEY_LIMIT_DEG:g})")
    if own > SELF_MIRROR_DEG:
        problems.append(f"its mirrored half is not the mirror image of its keyed half: {own:.0f} degrees apart (limit "
                        f"{SELF_MIRROR_DEG:g}; the mirror is not the body's: check the rig's left/right mapping)")
    elif p_mirrored > p_keyed + p_asym + MIRROR_MARGIN_DEG:
        problems.append(f"its mirrored half is {p_mirrored:.0f} degrees from the reference's other half, more than its "
                        f"keyed half's {p_keyed:.0f} plus the reference's own asymmetry {p_asym:.0f} plus "
                        f"{MIRROR_MARGIN_DEG:g} (the mirror is not the body's: check the rig's left/right mapping)")
    return p_mirrored, problems, own
