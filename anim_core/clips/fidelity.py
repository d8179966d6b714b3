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
  toes point).
* **Pose against the source** (the reference only): angles between bones (:data:`ANGLES`: knees, elbows, thighs
  and upper arms against the spine, the hip line against the shoulder line) of the character against the same
  angles of the source file's own forward kinematics at the same source time (``pose_error_deg``: the largest
  difference, named by angle and frame).  Bone lengths and rest poses differ between rigs; these angles do not.

A condition is compared with its reference instead: a frame whose angles differ from the reference's by more than
:data:`FOLD_DEG`, or whose head goes under its hips where the reference's does not, flips or folds the body.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

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
#: and bends knees (by at most half this, :data:`anim_core.clips.build.PLANT_LEG_TOLERANCE_DEG`; the shipped
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


def pose_angles(positions: Array) -> Array:
    """``(..., A)`` angles (radians, 0..pi) between the bone pairs of :data:`ANGLES` for positions ``(..., 31, 3)``."""
    p = np.asarray(positions, dtype=np.float64)
    bones = p[..., _A[:, :, 1], :] - p[..., _A[:, :, 0], :]  # (..., A, 2, 3)
    a, b = bones[..., 0, :], bones[..., 1, :]
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


def handedness(positions: Array) -> Array:
    """``(...)``: +1 where the left hip is on the body's left ("up x forward", forward where the toes point), -1
    where it is on the right, 0 where it cannot be told (no forward direction)."""
    p = np.asarray(positions, dtype=np.float64)
    toes = p[..., _FEET[:, 1], :] - p[..., _FEET[:, 0], :]
    forward = toes.sum(axis=-2)
    forward[..., 1] = 0.0
    left_dir = np.cross([0.0, 1.0, 0.0], forward)
    hips = p[..., _I["LeftUpLeg"], :] - p[..., _I["RightUpLeg"], :]
    return np.sign(np.sum(hips * left_dir, axis=-1))


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

    @property
    def ok(self) -> bool:
        return not self.problems

    def as_metrics(self) -> dict[str, float | None]:
        return {"upright_m": round(self.upright_m, 4), "foot_reach_m": round(self.foot_reach_m, 4),
                "under_floor_m": round(self.under_floor_m, 4), "handedness": round(self.handedness, 3),
                "pose_error_deg": None if self.pose_error_deg is None else round(self.pose_error_deg, 2)}

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
                    slack_deg: Array | None = None, source_frames: NDArray[np.intp] | None = None) -> Fidelity:
    """The gate on a reference clip: body checks on ``positions`` ``(T, 31, 3)`` (metres, on the floor;
    ``contact_heights`` ``(31,)`` the joints' heights above the soles standing) and its pose angles against
    ``source_positions`` ``(T, 31, 3)`` (the source's own forward kinematics at the same source times, any units
    and orientation), or against the closer of several such arrays per frame (a loop's seam fades between two
    cycles).  ``slack_deg`` ``(A,)``: what each angle may differ beyond :data:`POSE_LIMIT_DEG` by design (a loop
    of a stretch that does not end where it began is closed by spreading that difference over it).
    ``source_frames`` ``(T,)``: the source file's frame of each clip frame, named in the messages."""
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
    return Fidelity(up, reach, under, hand, worst, at, tuple(problems))


def check_condition(positions: Array, contact_heights: Array, reference: Array) -> Fidelity:
    """The gate on a condition's clip ``(T, 31, 3)`` against its reference on the same frames: it must not flip
    (head under the hips where the reference's is not) or fold (an angle of :data:`ANGLES` more than
    :data:`FOLD_DEG` from the reference's).  Its floor figures are reported, not gated: the reference's are."""
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
    return Fidelity(up, reach, under, hand, worst, f"{ANGLE_NAMES[angle]} at frame {frame}", tuple(problems))
