"""Mapping any common humanoid skeleton onto the CMU 31-joint skeleton the character is rigged for.

Conventions: the **canonical skeleton** is the CMU one (:data:`CANONICAL_NAMES`, :data:`CANONICAL_PARENTS`), Y up,
the character facing +Z with its left at +X, lengths in the source's units (``metres_per_unit`` says what they
are).  Every other part of anim_core that takes a BVH (clips, retargeting, foot contacts) takes it in that form, so
a source from another rig is first brought into it with :func:`normalize_bvh`.

Names are read as *side* + *stem* (:func:`split_side`): prefixes of Mixamo (``mixamorig:``, ``mixamorig_``,
``Armature_mixamorig``), Blender's ``DEF-``, 3ds Max's ``Bip01 `` and any ``namespace:``/``Armature|`` are dropped,
then a side is recognised as a word
(``Left``/``Right`` before or after the stem, any case), ``L_``/``R_``/``L `` prefixes, ``.L``/``_L``/``_l`` suffixes
(Blender, Unreal's ``thigh_l``), or a single letter glued to a capitalised stem (CMU's ``LHipJoint``, Poser/DAZ's
``lThigh``).  Stems give candidate roles; the hierarchy and the rest-pose bone lengths decide: a limb is the path
from the hips (legs) or the chest (arms: the joint where both arms' paths meet) to its end joint (``foot``/
``ankle``, ``hand``/``wrist``); the knee and elbow are the joints of that path that split it into two long parts,
the thigh and upper arm the joints that carry the length to them (so a ``Leg`` a few centimetres below the hip is
a helper, the knee on a ``Shin`` is the knee, and a ``Shoulder`` under a separate ``Collar`` is the upper arm).
Joints named ``twist``, ``roll``, ``helper``, ``corrective``, ``end``/``nub`` are never chosen for a limb.  Every
decision is recorded with its reason in :attr:`RigMapping.decisions`.

Joints of the source that map to nothing are reported (:attr:`RigMapping.unmapped`) and their rotations fold into
the nearest mapped joint below them: exact for helpers that do not rotate off the bone (twist bones, fixed
helpers), an approximation otherwise.
"""

from __future__ import annotations

import dataclasses
import json
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from ..io.bvh import OFFSET_MATCH, Bvh, bvh_from_poses, still_translation
from ..math.quat import identity, quat_conj, quat_from_axis_angle, quat_from_euler, quat_mul, rotate
from ..math.skeleton import Skeleton

Array = NDArray[np.float64]

CANONICAL_NAMES: tuple[str, ...] = (
    "Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
    "RHipJoint", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
    "LowerBack", "Spine", "Spine1", "Neck", "Neck1", "Head",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "LeftFingerBase", "LeftHandIndex1", "LThumb",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand", "RightFingerBase", "RightHandIndex1", "RThumb",
)
_PARENT_NAMES = {
    "LHipJoint": "Hips", "LeftUpLeg": "LHipJoint", "LeftLeg": "LeftUpLeg", "LeftFoot": "LeftLeg",
    "LeftToeBase": "LeftFoot", "LowerBack": "Hips", "Spine": "LowerBack", "Spine1": "Spine", "Neck": "Spine1",
    "Neck1": "Neck", "Head": "Neck1", "LeftShoulder": "Spine1", "LeftArm": "LeftShoulder",
    "LeftForeArm": "LeftArm", "LeftHand": "LeftForeArm", "LeftFingerBase": "LeftHand",
    "LeftHandIndex1": "LeftFingerBase", "LThumb": "LeftHand",
}
_PARENT_NAMES |= {k.replace("Left", "Right").replace("LH", "RH").replace("LT", "RT"):
                  v.replace("Left", "Right").replace("LH", "RH") for k, v in list(_PARENT_NAMES.items())}
CANONICAL_PARENTS: NDArray[np.intp] = np.array(
    [-1] + [CANONICAL_NAMES.index(_PARENT_NAMES[n]) for n in CANONICAL_NAMES[1:]], dtype=np.intp)
#: Parts without which the character cannot be driven, each with the canonical joints it needs.
REQUIRED_PARTS: dict[str, tuple[str, ...]] = {
    "hips": ("Hips",), "spine": ("Spine1",), "head": ("Head",),
    "left leg": ("LeftUpLeg", "LeftLeg", "LeftFoot"), "right leg": ("RightUpLeg", "RightLeg", "RightFoot"),
    "left arm": ("LeftArm", "LeftForeArm", "LeftHand"), "right arm": ("RightArm", "RightForeArm", "RightHand"),
}
#: Limits on what a source may hold, so hostile files fail fast instead of exhausting memory.
MAX_JOINTS = 1000
MAX_FRAMES = 1_000_000

_PREFIX = re.compile(r"^(?:.*[:|])?(?:armature_?)?(?:mixamorig[_:]?)?(?:def[-_])?(?:bip0*1[ _])?", re.IGNORECASE)
# (pattern, side group, strong): a strong marker without a partner is an error in mirroring, a weak one is central.
_SIDES: tuple[tuple[re.Pattern[str], bool], ...] = (
    (re.compile(r"^(?P<side>left|right)(?=[^a-z]|$)[ _.]?", re.IGNORECASE), True),
    (re.compile(r"^(?P<side>left|right)", re.IGNORECASE), True),
    (re.compile(r"[ _.]?(?P<side>left|right)$", re.IGNORECASE), True),
    (re.compile(r"^(?P<side>[LRlr])[_. ]"), True),
    (re.compile(r"[_.](?P<side>[LRlr])$"), True),
    (re.compile(r"^(?P<side>[LRlr])(?=[A-Z])"), False),
)
_HELPER = re.compile(r"twist|roll|helper|corrective|adj|nub|end$|site|ik|pole|target", re.IGNORECASE)


class RigMapError(ValueError):
    """A skeleton that cannot be mapped onto the character (missing parts, inconsistent explicit mapping)."""


@dataclass(frozen=True)
class SideName:
    """A joint name read as side (``"L"``, ``"R"`` or ``None``), stem (lowercase letters and digits) and a
    ``pattern`` with ``{}`` where the side marker was (the partner's name is ``pattern`` with the other marker)."""

    side: str | None
    stem: str
    pattern: str
    marker: str
    strong: bool


def split_side(name: str) -> SideName:
    """Read a joint name as side + stem; see the module docstring for the recognised conventions."""
    prefix = _PREFIX.match(name).group(0)  # type: ignore[union-attr]
    rest = name[len(prefix):] or name
    if rest is name:
        prefix = ""
    for pattern, strong in _SIDES:
        m = pattern.search(rest)
        if m and m.group(0) != rest:
            marker = m.group("side")
            side = "L" if marker[0] in "Ll" else "R"
            a, b = m.span("side")
            stem = re.sub(r"[^a-z0-9]", "", (rest[:m.start()] + rest[m.end():]).lower())
            return SideName(side, stem, prefix + rest[:a] + "{}" + rest[b:], marker, strong)
    return SideName(None, re.sub(r"[^a-z0-9]", "", rest.lower()), name, "", False)


def _partner_marker(marker: str) -> str:
    table = {"l": "r", "r": "l", "left": "right", "right": "left"}
    other = table[marker.lower()]
    if marker.isupper() and len(marker) > 1:
        return other.upper()
    return other.capitalize() if marker[0].isupper() else other


def partner_name(name: str) -> str | None:
    """The name of the joint's left/right partner, ``None`` for a central joint."""
    s = split_side(name)
    return None if s.side is None else s.pattern.replace("{}", _partner_marker(s.marker), 1)


# ---------------------------------------------------------------------------------------------------------------
# Roles from stems

_ROLE_STEMS: dict[str, tuple[str, ...]] = {
    "hipjoint": ("hipjoint", "pelvis", "pelvisside"),
    "upleg": ("upleg", "thigh", "upperleg", "hip", "thighbend", "femur"),
    "knee": ("leg", "calf", "shin", "knee", "lowerleg", "tibia"),
    "foot": ("foot", "ankle"),
    "toe": ("toebase", "toe", "toes", "ball", "foot", "toe0", "toe01"),
    "collar": ("collar", "clavicle", "shoulder"),
    "arm": ("arm", "upperarm", "shldr", "shoulder", "shldrbend", "humerus"),
    "elbow": ("forearm", "lowerarm", "elbow", "forearmbend"),
    "hand": ("hand", "wrist"),
    "thumb": ("thumb", "thumb1", "thumb01", "handthumb"),
    "fingerbase": ("fingerbase", "palm", "handpalm", "hand", "metacarpal"),  # looked for below the hand only
    "index": ("handindex1", "index", "index1", "index01", "indexfinger1", "finger", "handindex", "findex",
              "handfinger"),  # "handfinger": the MakeHuman cmu_mb rig's LeftHandFinger1
}
_CENTRAL_HIPS = ("hips", "hip", "pelvis")
_CENTRAL_HEAD = ("head",)


def _has_role(stem: str, role: str) -> bool:
    base = re.sub(r"\d+$", "", stem)
    return stem in _ROLE_STEMS[role] or base in _ROLE_STEMS[role]


@dataclass(frozen=True)
class Decision:
    """One canonical joint: the source joint it reads (``None``: synthesised, zero length, no rotation) and why."""

    canonical: str
    source: str | None
    reason: str


@dataclass(frozen=True, eq=False)
class RigMapping:
    """Which source joint drives each canonical joint.

    ``source_index``: ``(31,)`` source joint index per canonical joint, ``-1`` where none; ``decisions``: per
    canonical joint, what was chosen and why; ``unmapped``: source joints that drive nothing; ``convention``: the
    naming convention(s) recognised.
    """

    source_names: tuple[str, ...]
    source_index: NDArray[np.intp]
    decisions: tuple[Decision, ...]
    unmapped: tuple[str, ...]
    convention: str

    def as_dict(self) -> dict[str, str]:
        """``{canonical: source}`` for the mapped joints (the format of an explicit mapping file)."""
        return {d.canonical: d.source for d in self.decisions if d.source is not None}


CONVENTIONS: dict[str, re.Pattern[str]] = {
    "Mixamo": re.compile(r"mixamorig", re.IGNORECASE),
    "Unreal": re.compile(r"^(pelvis|thigh_[lr]|calf_[lr]|upperarm_[lr]|lowerarm_[lr]|clavicle_[lr]|spine_0\d)$"),
    "Blender": re.compile(r"\.[LR]$"),
    "Poser/DAZ": re.compile(r"^[lr](Thigh|Shin|Collar|Shldr|ForeArm|Foot|Hand|Toe)"),
    "SMPL": re.compile(r"^([LR]_(Hip|Knee|Ankle|Collar|Shoulder|Elbow|Wrist)|Pelvis|Spine[123])$"),
    "CMU": re.compile(r"^(LHipJoint|RHipJoint|LowerBack|Neck1|LeftFingerBase|LThumb|RThumb)$"),
    "Left/Right words": re.compile(r"(^|[^a-z])(Left|Right)|(Left|Right)$", re.IGNORECASE),
    "L_/R_ and _L/_R": re.compile(r"^[LRlr]_|_[LRlr]$"),
}


def detect_convention(names: Sequence[str]) -> str:
    """The naming conventions the names follow, most specific first (``"Mixamo + Poser/DAZ"`` for a mix)."""
    found: list[str] = []
    for label, pattern in CONVENTIONS.items():
        hits = sum(bool(pattern.search(n)) for n in names)
        if hits >= 2 or (label == "Mixamo" and hits):
            found.append(label)
    specific = [f for f in found if f not in ("Left/Right words", "L_/R_ and _L/_R")]
    return " + ".join(specific or found) or "unknown"


def _chain(parents: NDArray[np.intp], j: int, stop: int) -> list[int]:
    """Joints from ``stop`` (exclusive) down to ``j`` (inclusive); empty if ``stop`` is not an ancestor."""
    out = []
    while j != stop:
        if j < 0:
            return []
        out.append(j)
        j = int(parents[j])
    return out[::-1]


def _lca(parents: NDArray[np.intp], a: int, b: int) -> int:
    ancestors = set()
    while a >= 0:
        ancestors.add(a)
        a = int(parents[a])
    while b not in ancestors:
        b = int(parents[b])
    return b


def _straight(pos: Array, path: list[int], a: int, b: int, tolerance: float = 0.05) -> bool:
    """Do the joints of ``path`` between positions ``a`` and ``b`` lie on the segment ``a``..``b``?"""
    seg = pos[b] - pos[a]
    length = np.linalg.norm(seg)
    if length < 1e-12:
        return False
    i, k = path.index(a), path.index(b)
    for j in path[i + 1:k]:
        v = pos[j] - pos[a]
        t = np.clip(v @ seg / length**2, 0.0, 1.0)
        if np.linalg.norm(v - t * seg) > tolerance * length:
            return False
    return True


class _Mapper:
    def __init__(self, names: Sequence[str], parents: NDArray[np.intp], rest_positions: Array) -> None:
        self.names = tuple(names)
        self.parents = parents
        self.pos = rest_positions
        self.sides = [split_side(n) for n in names]
        self.helper = [bool(_HELPER.search(s.stem)) for s in self.sides]
        depth = np.zeros(len(names), dtype=np.intp)
        for j in range(1, len(names)):
            depth[j] = depth[parents[j]] + 1
        self.depth = depth
        self.map: dict[str, int] = {}
        self.why: dict[str, str] = {}

    def set(self, canonical: str, j: int | None, reason: str) -> None:
        if j is not None and j >= 0:
            self.map[canonical] = j
            self.why[canonical] = reason

    def named(self, role: str, side: str | None, among: Sequence[int] | None = None) -> list[int]:
        joints = range(len(self.names)) if among is None else among
        return [j for j in joints if self.sides[j].side == side and not self.helper[j]
                and _has_role(self.sides[j].stem, role)]

    def top(self, joints: list[int]) -> int | None:
        return min(joints, key=lambda j: (self.depth[j], j)) if joints else None

    def dist(self, a: int, b: int) -> float:
        return float(np.linalg.norm(self.pos[a] - self.pos[b]))

    def limb(self, side: str, base: int, end: int, prefix: str, kinds: tuple[str, str, str]) -> None:
        """Map a leg (``kinds`` = upleg, knee, hipjoint) or an arm (arm, elbow, collar) from ``base`` to ``end``."""
        upper_role, middle_role = kinds[:2]
        canon = {"upleg": ("UpLeg", "Leg", "HipJoint"), "arm": ("Arm", "ForeArm", "Shoulder")}[upper_role]
        path = _chain(self.parents, end, base)[:-1]  # joints between base and end
        ok = [j for j in path if not self.helper[j]]
        if not ok:
            return
        by_name = self.named(middle_role, side, ok)
        candidates = by_name or ok

        # The middle joint (knee, elbow) splits the limb into two long parts.
        def split(j: int) -> float:
            return min(self.dist(base, j), self.dist(j, end))
        middle = max(candidates, key=split)
        how = "named " + repr(self.names[middle]) if by_name else "no joint named like it"
        self.set(prefix + canon[1], middle, f"{how}; of the joints between {self.names[base]!r} and "
                                           f"{self.names[end]!r} it splits the limb into the two longest parts "
                                           f"({split(middle):.3g} units each at least)")
        before = [j for j in ok if path.index(j) < path.index(middle)]
        if not before:
            return
        lower = self.dist(middle, end)
        girdles = self.named("collar" if upper_role == "arm" else "hipjoint", side, before)
        if upper_role == "arm":
            # "shoulder" names the collar unless a collar/clavicle precedes it; then it is the upper arm.
            explicit = [j for j in girdles if self.sides[j].stem.rstrip("0123456789") in ("collar", "clavicle")]
            named_upper = [j for j in self.named("arm", side, before)
                           if not (self.sides[j].stem.startswith("shoulder") and not explicit
                                   and any(k != j for k in self.named("arm", side, before)))]
            named_upper = [j for j in named_upper if not explicit or path.index(j) > path.index(explicit[-1])]
        else:
            named_upper = [j for j in self.named("upleg", side, before) if j not in girdles]

        def carries(j: int) -> bool:
            ratio = self.dist(j, middle) / max(lower, 1e-12)
            return 0.55 <= ratio <= 2.0 and _straight(self.pos, path, j, middle)
        valid_named = [j for j in named_upper if carries(j)]
        if valid_named:
            upper = valid_named[0]
            reason = (f"named {self.names[upper]!r}; carries the length to {self.names[middle]!r} "
                      f"({self.dist(upper, middle):.3g} vs {lower:.3g} below)")
        else:
            valid = [j for j in before if carries(j)]
            if not valid:
                upper = before[-1]
                reason = "the joint just above the middle joint (no joint carries a plausible length)"
            else:
                upper = valid[0]
                reason = (f"first joint from which the path to {self.names[middle]!r} is straight and as long as "
                          f"the part below ({self.dist(upper, middle):.3g} vs {lower:.3g})"
                          + (f"; named joints {[self.names[j] for j in named_upper]} do not" if named_upper else ""))
        self.set(prefix + canon[0], upper, reason)
        above = [j for j in path if path.index(j) < path.index(upper)]
        girdle_name = (("L" if side == "L" else "R") + "HipJoint") if upper_role == "upleg" else prefix + "Shoulder"
        if above:
            self.set(girdle_name, above[-1], f"the joint above {self.names[upper]!r} on the path from "
                                             f"{self.names[base]!r} (carries the "
                                             f"{'pelvis' if upper_role == 'upleg' else 'collar'} bone)")

    def run(self) -> None:
        sides = {"L": "Left", "R": "Right"}
        hips_named = [j for j in range(len(self.names)) if self.sides[j].side is None
                      and self.sides[j].stem in _CENTRAL_HIPS]
        feet = {s: self.top(self.named("foot", s)) for s in sides}
        hands = {s: self.top(self.named("hand", s)) for s in sides}
        if feet["L"] is not None and feet["R"] is not None:
            lca = _lca(self.parents, feet["L"], feet["R"])
            hips = self.top([j for j in hips_named if j == lca or _chain(self.parents, lca, j)])
            if hips is None:
                hips = lca
                self.set("Hips", hips, "where the paths to both feet meet")
            else:
                self.set("Hips", hips, f"named {self.names[hips]!r}, above both feet")
        elif hips_named:
            hips = self.top(hips_named)
            self.set("Hips", hips, f"named {self.names[hips]!r}")
        else:
            return
        for s, word in sides.items():
            foot = feet[s]
            if foot is not None and _chain(self.parents, foot, hips):
                self.set(word + "Foot", foot, f"named {self.names[foot]!r} (the highest {word.lower()} foot/ankle)")
                self.limb(s, hips, foot, word, ("upleg", "knee", "hipjoint"))
                toes = [c for c in range(foot + 1, len(self.names)) if self.parents[c] == foot and not self.helper[c]]
                named = self.named("toe", s, toes)
                toe = (named or toes or [None])[0]
                if toe is not None:
                    self.set(word + "ToeBase", toe, f"{'named ' if named else ''}{self.names[toe]!r}, "
                                                    f"child of the foot")
        present = [h for h in hands.values() if h is not None]
        if not present:
            return
        if len(present) == 2:
            chest = _lca(self.parents, *present)
        else:  # one arm: the chest is the first branching joint above its hand
            chest = int(self.parents[present[0]])
            while chest > 0 and len([c for c in range(len(self.names)) if self.parents[c] == chest]) < 2:
                chest = int(self.parents[chest])
        if chest != hips and _chain(self.parents, chest, hips):
            self.set("Spine1", chest, "where the paths to both hands meet (the chest)")
            spine = [j for j in _chain(self.parents, chest, hips)[:-1]]
            if len(spine) >= 2:
                self.set("LowerBack", spine[0], "first spine joint above the hips")
            if spine:
                self.set("Spine", spine[-1], "last spine joint below the chest"
                         + (f"; {[self.names[j] for j in spine[1:-1]]} fold into it" if len(spine) > 2 else ""))
        else:
            chest = hips
        head = self.top([j for j in range(len(self.names)) if self.sides[j].side is None and not self.helper[j]
                         and self.sides[j].stem in _CENTRAL_HEAD and _chain(self.parents, j, chest)])
        if head is not None:
            self.set("Head", head, f"named {self.names[head]!r}, above the chest")
            neck = _chain(self.parents, head, chest)[:-1]
            if len(neck) >= 2:
                self.set("Neck", neck[0], "first joint above the chest towards the head")
            if neck:
                self.set("Neck1", neck[-1], "joint below the head")
        for s, word in sides.items():
            hand = hands[s]
            if hand is None or not _chain(self.parents, hand, chest):
                continue
            self.set(word + "Hand", hand, f"named {self.names[hand]!r} (the highest {word.lower()} hand/wrist)")
            self.limb(s, chest, hand, word, ("arm", "elbow", "collar"))
            below = [c for c in range(hand + 1, len(self.names)) if _chain(self.parents, c, hand)]
            thumb = self.top(self.named("thumb", s, below))
            base = self.top(self.named("fingerbase", s, below))
            self.set(word + "FingerBase", base, "named finger base under the hand")
            if base is not None:
                below = [c for c in below if _chain(self.parents, c, base)]
            index = self.top(self.named("index", s, below))
            self.set(("L" if s == "L" else "R") + "Thumb", thumb, "first thumb joint under the hand")
            if index is not None:
                self.set(word + "HandIndex1", index, "first index/finger joint under the hand")


# ---------------------------------------------------------------------------------------------------------------
# Mapping by structure (joints without telling names)

#: A branch of a joint counts as a limb or the trunk when it holds at least two joints and reaches at least this
#: share of the figure's size (its largest extent) from the joint: fingers (a twentieth of the height) and single
#: helpers do not, legs, arms and the neck with the head do.
BRANCH_REACH = 0.08
#: The legs' sockets and the upper arms stand this share of the figure's size in front of the spine at least (the
#: spine runs along the back), or the facing, and with it left and right, is not told apart.
FACING_MIN = 0.01


def _branches(children: list[list[int]], below: list[list[int]], pos: Array, j: int, size: float) -> list[int]:
    """The children of ``j`` whose subtrees are limbs or the trunk (:data:`BRANCH_REACH`)."""
    return [c for c in children[j] if len(below[c]) >= 2
            and np.linalg.norm(pos[below[c]] - pos[j], axis=1).max() >= BRANCH_REACH * size]


def _main_chain(parents: NDArray[np.intp], below: list[int], pos: Array, base: int) -> list[int]:
    """The joints from the branch's first joint down to its joint farthest from ``base``."""
    tip = below[int(np.argmax(np.linalg.norm(pos[below] - pos[base], axis=1)))]
    return _chain(parents, tip, base)


def _end_of_chain(chain: list[int], children: list[list[int]], pos: Array, start: float) -> int:
    """A hand or head on its chain: the first joint from ``start`` (share of the chain's length) on that branches
    (fingers; eyes and jaw), else the last joint, or the one before it when the last bone is an end joint (longer
    than one and a half times the bone before it, as ``HeadTop_End``; shorter than half of it, as a hand's end)."""
    lengths = np.linalg.norm(np.diff(pos[chain], axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(lengths)])
    for k, j in enumerate(chain):
        if along[k] >= start * along[-1] and len(children[j]) >= 2:
            return j
    if len(chain) >= 3 and not children[chain[-1]] and (lengths[-1] > 1.5 * lengths[-2]
                                                          or lengths[-1] < 0.5 * lengths[-2]):
        return chain[-2]
    return chain[-1]


def structural_anchors(parents: NDArray[np.intp], positions: Array) -> dict[str, int]:
    """Hips, chest, feet, hands and head of a humanoid skeleton whose joint names say nothing, from its structure
    and the geometry of one pose (the bind or rest pose), keyed ``"Hips"``, ``"Spine1"``, ``"LeftFoot"``, ...

    Structure: the hips are the highest joint with three branches (:data:`BRANCH_REACH`), two legs and a spine;
    the chest is the highest joint of the spine with three branches, two arms and the neck, the neck being the
    branch that keeps closest to the hips-to-chest line.  A foot is the joint of its leg below half the leg's drop
    from which the bone goes more across than down (to the toes), else the leg's last joint; a hand or the head
    the first joint of its chain that branches, else its last joint short of an end joint
    (:func:`_end_of_chain`); an elbow the joint that splits the straight stretch of the arm ending at the hand
    (``"LeftForeArm"``, left out where the arm has no straight stretch: the limb's lengths decide then).
    Left and right from geometry, not from the feet: up runs from the hips to the head; the legs' sockets and the
    shoulders stand in front of the spine, which runs along the back (:data:`FACING_MIN`), so forward is from the
    spine to them; left is up × forward.  ``positions``: ``(J, 3)``.
    Raises :class:`RigMapError` saying what is ambiguous.
    """
    pos = np.asarray(positions, dtype=np.float64)
    n = len(parents)
    children: list[list[int]] = [[] for _ in range(n)]
    for j in range(1, n):  # once per skeleton, not per frame
        children[int(parents[j])].append(j)
    below: list[list[int]] = [[j] for j in range(n)]
    for j in range(n - 1, 0, -1):  # parents before children: each subtree is complete when its root is reached
        below[int(parents[j])].extend(below[j])
    size = float(np.ptp(pos, axis=0).max())
    if size <= 0:
        raise RigMapError("all joints are at one place: no structure to map")
    three = [j for j in range(n) if len(_branches(children, below, pos, j, size)) >= 3]
    if not three:
        raise RigMapError("no joint has three branches (two legs and a spine): not a humanoid tree")
    depth = np.array([len(_chain(parents, j, -1)) for j in range(n)])
    hips = min(three, key=lambda j: (depth[j], j))
    hip_branches = _branches(children, below, pos, hips, size)
    spines = [c for c in hip_branches if any(j in three for j in below[c])]
    if len(hip_branches) != 3 or len(spines) != 1:
        raise RigMapError(f"the hips (joint {hips}) have {len(hip_branches)} branches, {len(spines)} of them with "
                          f"arms and a neck; two legs and one spine are needed to map by structure")
    chest = min((j for j in below[spines[0]] if j in three), key=lambda j: (depth[j], j))
    arm_branches = _branches(children, below, pos, chest, size)
    if len(arm_branches) != 3:
        raise RigMapError(f"the chest (joint {chest}) has {len(arm_branches)} branches; two arms and a neck are "
                          f"needed to map by structure")
    up = pos[chest] - pos[hips]
    if np.linalg.norm(up) < 1e-12:
        raise RigMapError(f"the hips (joint {hips}) and the chest (joint {chest}) are at one place: no up")
    up /= np.linalg.norm(up)

    def across(v: Array) -> Array:
        return v - (v @ up)[..., None] * up
    lateral = [float(np.linalg.norm(across(pos[below[c]] - pos[chest]), axis=1).max()) for c in arm_branches]
    order = np.argsort(lateral)
    if lateral[order[0]] > 0.5 * lateral[order[1]]:
        raise RigMapError(f"of the chest's (joint {chest}) branches none keeps clearly closer to the spine's line "
                          f"than the others (reach across {', '.join(f'{x:.3g}' for x in lateral)}): the neck is "
                          f"not told from the arms")
    neck = arm_branches[int(order[0])]
    arms = [c for c in arm_branches if c != neck]
    legs = [c for c in hip_branches if c != spines[0]]

    def foot(branch: int) -> int:
        chain = _main_chain(parents, below[branch], pos, hips)
        height = (pos[chain] - pos[hips]) @ up
        for k in range(len(chain) - 1):
            d = pos[chain[k + 1]] - pos[chain[k]]
            if height[k] < 0.5 * height.min() and abs(d @ up) < np.linalg.norm(across(d)):
                return chain[k]
        return chain[-1]
    feet = [foot(c) for c in legs]
    hands = [_end_of_chain(_main_chain(parents, below[c], pos, chest), children, pos, 0.5) for c in arms]
    head = _end_of_chain(_main_chain(parents, below[neck], pos, chest), children, pos, 0.0)

    # Facing: the legs' sockets and the shoulders stand in front of the spine.  Up now from the hips to the head
    # (closer to the vertical than the chest, which sits back), and each compared with the spine joint at its
    # height, so that little of a height difference leaks into "forward" through a leaning trunk.
    up = pos[head] - pos[hips]
    up /= max(float(np.linalg.norm(up)), 1e-12)

    def socket(branch: int) -> int:  # the last joint of the leg at the hips' level (a quarter of its drop)
        chain = _main_chain(parents, below[branch], pos, hips)
        height = (pos[chain] - pos[hips]) @ up
        return chain[int(np.flatnonzero(height >= 0.25 * height.min()).max())]

    def shoulder(branch: int) -> int:  # the last joint of the arm within a third of its reach across the trunk
        chain = _main_chain(parents, below[branch], pos, chest)
        far = np.linalg.norm(across(pos[chain] - pos[chest]), axis=1)
        return chain[int(np.flatnonzero(far <= far.max() / 3).max())]
    sockets = [socket(c) for c in legs]
    shoulders = [shoulder(c) for c in arms]
    spine = _chain(parents, chest, hips)
    low_back = spine[0] if len(spine) > 1 else hips
    forward = across(pos[sockets].mean(axis=0) - pos[low_back]) + across(pos[shoulders].mean(axis=0) - pos[chest])
    if np.linalg.norm(forward) < FACING_MIN * size:
        raise RigMapError(f"the legs' sockets and the shoulders stand {np.linalg.norm(forward):.3g} units in front "
                          f"of the spine, less than {FACING_MIN:.0%} of the figure's size: left and right cannot be "
                          f"told from the geometry")
    left = np.cross(up, forward / np.linalg.norm(forward))
    def elbow(hand: int) -> int | None:
        """The elbow: within the straight stretch of the arm that ends at the hand (upper arm and forearm; the
        collar bone leaves it), the joint that splits it into the two longest parts.  Lengths alone do not tell:
        CMU's forearm is shorter than its collar bone."""
        chain = _chain(parents, hand, chest)
        for a in chain[:-2]:
            if _straight(pos, chain, a, hand):
                inner = chain[chain.index(a) + 1:-1]
                return max(inner, key=lambda j: min(np.linalg.norm(pos[j] - pos[a]),
                                                    np.linalg.norm(pos[hand] - pos[j])))
        return None
    elbows = [elbow(h) for h in hands]
    out = {"Hips": hips, "Spine1": chest, "Head": head}
    for what, pair, at in (("Foot", feet, sockets), ("Hand", hands, shoulders), ("ForeArm", elbows, shoulders)):
        d = pos[at[0]] - pos[at[1]]
        side = float(d @ left)
        if abs(side) < 0.5 * np.linalg.norm(d):
            raise RigMapError(f"the two {'legs' if what == 'Foot' else 'arms'} (joints {at[0]} and {at[1]}) are not "
                              f"side by side across the facing: left and right cannot be told from the geometry")
        first, second = pair if side > 0 else pair[::-1]
        if first is not None and second is not None:
            out["Left" + what], out["Right" + what] = first, second
    return out


class _StructureMapper(_Mapper):
    """The name-based mapper run on :func:`structural_anchors`: the anchors play named feet, hands, hips and head;
    every other joint has no telling name, so limbs are split by their lengths alone."""

    def __init__(self, names: Sequence[str], parents: NDArray[np.intp], rest_positions: Array) -> None:
        super().__init__(names, parents, rest_positions)
        self.anchors = structural_anchors(parents, rest_positions)
        roles = {"Hips": (None, "hips"), "Head": (None, "head"), "LeftFoot": ("L", "foot"),
                 "RightFoot": ("R", "foot"), "LeftHand": ("L", "hand"), "RightHand": ("R", "hand"),
                 "LeftForeArm": ("L", "forearm"), "RightForeArm": ("R", "forearm")}
        self.sides = [SideName(None, "joint", n, "", False) for n in names]
        for canonical, (side, stem) in roles.items():
            if canonical in self.anchors:
                self.sides[self.anchors[canonical]] = SideName(side, stem, names[self.anchors[canonical]], "", True)
        self.helper = [False] * len(names)

    running = False

    def run(self) -> None:
        self.running = True  # the choices made here are the structure's; explicit entries set later are not
        try:
            super().run()
        finally:
            self.running = False

    def set(self, canonical: str, j: int | None, reason: str) -> None:
        if not self.running:
            super().set(canonical, j, reason)
            return
        if canonical in ("LeftForeArm", "RightForeArm") and canonical in self.anchors:
            reason = "the joint that splits the arm's straight stretch (upper arm and forearm) into its two parts"
        elif canonical in ("Hips", "Head", "LeftFoot", "RightFoot", "LeftHand", "RightHand", "Spine1"):
            reason = {"Hips": "the joint where two legs and the spine branch",
                      "Spine1": "the joint where two arms and the neck branch",
                      "Head": "the end of the neck's branch"}.get(
                canonical, "the end of its limb; left and right from the bind-pose geometry (up along the spine, "
                           "forward from the spine to the hip sockets and shoulders)")
        super().set(canonical, j, f"by structure (no joint names to go by): {reason}")


def map_skeleton(skeleton: Skeleton, explicit: Mapping[str, str] | None = None,
                 positions: Array | None = None) -> RigMapping:
    """Map ``skeleton``'s joints onto the canonical (CMU) joints; ``explicit`` ``{canonical: source}`` wins.

    ``positions``: ``(J, 3)`` joint positions of a pose to measure distances in (default: the rest pose; a motion
    frame for rigs whose rest pose is not a human pose).  Raises :class:`RigMapError` naming the missing parts if
    hips, spine, head, legs or arms cannot be found, and
    if an explicit entry names an unknown joint or contradicts the hierarchy.
    """
    names = skeleton.names
    if skeleton.n_joints > MAX_JOINTS:
        raise RigMapError(f"the skeleton has {skeleton.n_joints} joints; at most {MAX_JOINTS} are supported")
    rest_pos = skeleton.rest_global()[1] if positions is None else np.asarray(positions, dtype=np.float64)
    mapper = _Mapper(names, skeleton.parents, rest_pos)
    mapper.run()
    structure_error: RigMapError | None = None
    if not mapper.map:
        # No name told anything (exporters' "joint0", "joint1", ...): the tree's shape and the pose do.
        try:
            mapper = _StructureMapper(names, skeleton.parents, rest_pos)
            mapper.run()
        except RigMapError as exc:
            structure_error = exc
    for canonical, source in (explicit or {}).items():
        if canonical not in CANONICAL_NAMES:
            raise RigMapError(f"explicit mapping names {canonical!r}, which is not a character joint; they are "
                              f"{', '.join(CANONICAL_NAMES)}")
        if source in (None, ""):
            mapper.map.pop(canonical, None)
            mapper.why[canonical] = "left out by the explicit mapping"
            continue
        if source not in names:
            raise RigMapError(f"explicit mapping maps {canonical!r} to {source!r}, which is not a joint of the "
                              f"skeleton")
        j = names.index(source)
        for other in [c for c, k in mapper.map.items() if k == j and c != canonical]:
            del mapper.map[other]
            mapper.why[other] = f"its automatic choice {source!r} was given to {canonical!r} by the explicit mapping"
        mapper.set(canonical, j, "explicit mapping")
    # The same source joint may drive only one canonical joint (the last writer above wins per canonical joint).
    used: dict[int, str] = {}
    for canonical in CANONICAL_NAMES:
        j = mapper.map.get(canonical)
        if j is not None and j in used:
            raise RigMapError(f"source joint {names[j]!r} is mapped to both {used[j]!r} and {canonical!r}")
        if j is not None:
            used[j] = canonical
    # Hierarchy: each mapped joint must lie below the source joint of its nearest mapped canonical ancestor.
    for c, canonical in enumerate(CANONICAL_NAMES):
        j = mapper.map.get(canonical)
        p = int(CANONICAL_PARENTS[c])
        while p >= 0 and CANONICAL_NAMES[p] not in mapper.map:
            p = int(CANONICAL_PARENTS[p])
        if j is not None and p >= 0 and not _chain(skeleton.parents, j, mapper.map[CANONICAL_NAMES[p]]):
            raise RigMapError(f"{canonical!r} is mapped to {names[j]!r}, which is not below "
                              f"{names[mapper.map[CANONICAL_NAMES[p]]]!r} (mapped to {CANONICAL_NAMES[p]!r})")
    missing = [part for part, joints in REQUIRED_PARTS.items() if any(n not in mapper.map for n in joints)]
    if missing:
        detail = "; ".join(f"{part}: {', '.join(n for n in REQUIRED_PARTS[part] if n not in mapper.map)}"
                           for part in missing)
        by_structure = f"; mapping by structure failed: {structure_error}" if structure_error else ""
        raise RigMapError(f"cannot find the {', '.join(missing)} of the skeleton (missing {detail}{by_structure}); "
                          f"give them in an explicit mapping (character joint = source joint)")
    # The bones that carry the limbs' and the trunk's lengths must have a length.
    short = [f"{a}-{b} ({names[mapper.map[a]]!r}-{names[mapper.map[b]]!r})"
             for a, b in (("LeftUpLeg", "LeftLeg"), ("LeftLeg", "LeftFoot"), ("RightUpLeg", "RightLeg"),
                          ("RightLeg", "RightFoot"), ("LeftArm", "LeftForeArm"), ("LeftForeArm", "LeftHand"),
                          ("RightArm", "RightForeArm"), ("RightForeArm", "RightHand"), ("Hips", "Head"))
             if mapper.dist(mapper.map[a], mapper.map[b]) < 1e-9]
    if short:
        raise RigMapError(f"zero-length bones where the character needs a length: {', '.join(short)}")
    index = np.array([mapper.map.get(n, -1) for n in CANONICAL_NAMES], dtype=np.intp)
    decisions = tuple(Decision(n, names[mapper.map[n]] if n in mapper.map else None,
                               mapper.why.get(n, "not found: synthesised with zero length and no rotation"))
                      for n in CANONICAL_NAMES)
    unmapped = tuple(n for j, n in enumerate(names) if j not in used)
    return RigMapping(names, index, decisions, unmapped, detect_convention(names))


def read_mapping_file(path: str | Path) -> dict[str, str]:
    """An explicit mapping ``{character joint: source joint}`` from a ``.toml`` (table ``[mapping]`` or top level)
    or ``.json`` file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
        data = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:  # RecursionError: nested too deeply
        raise RigMapError(f"{path}: cannot read the mapping: {exc}") from None
    data = data.get("mapping", data) if isinstance(data, dict) else data
    if not isinstance(data, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
        raise RigMapError(f"{path}: a mapping is a table of character joint = source joint strings")
    return dict(data)


# ---------------------------------------------------------------------------------------------------------------
# Units and up axis

#: Metres per unit and the plausible range of a standing humanoid's rest-pose height (joints only) in that unit.
UNITS: dict[str, tuple[float, tuple[float, float]]] = {
    "m": (1.0, (0.9, 2.4)),
    "inch": (0.0254, (36.0, 89.9)),
    "cm": (0.01, (90.0, 240.0)),
    "mm": (0.001, (900.0, 2400.0)),
    # CMU's BVH conversions: 1 unit = (1 / 0.45) inches.
    "cmu": (0.0254 / 0.45, (15.0, 35.0)),
}


def detect_up_axis(rest_positions: Array, head: int, hips: int) -> str:
    """``"y"`` or ``"z"``: the axis along which the head stands above the hips (most)."""
    d = rest_positions[head] - rest_positions[hips]
    return "y" if abs(d[1]) >= abs(d[2]) else "z"


def detect_units(height: float) -> str:
    """The unit in which ``height`` (rest-pose joint extent along up) is a plausible human height."""
    for unit, (_, (lo, hi)) in UNITS.items():
        if lo <= height <= hi:
            return unit
    raise RigMapError(f"a rest-pose height of {height:.4g} units is not a human height in m, cm, mm, inches or CMU "
                      f"units; give the units explicitly")


def units_from_height(height: float, what: str = "skinned mesh") -> str:
    """The unit in which a figure ``height`` tall (``what``: a skinned mesh's bounding box along up, head and feet
    included) is a plausible human height (the ranges of :data:`UNITS`)."""
    for unit, (_, (lo, hi)) in UNITS.items():
        if lo <= height <= hi:
            return unit
    raise RigMapError(f"a {what} {height:.4g} units tall is not a human height in m, cm, mm, inches or CMU units; "
                      f"give the units explicitly")


def canonical_frame(rest_positions: Array, source_index: NDArray[np.intp], up_axis: str | None = None,
                    units: str | None = None) -> tuple[Array, str, str, float]:
    """The turn that brings a source skeleton into the canonical world (Y up, its left at +X), and its units.

    ``rest_positions``: ``(J, 3)`` source joint positions at rest; ``source_index``: a :class:`RigMapping`'s
    ``source_index``; ``up_axis``/``units`` override the detection.  Returns ``(world, up_axis, units, facing)``:
    ``world`` the quaternion (w, x, y, z) to apply to source positions, ``facing`` the turn about up (radians).
    """
    idx = source_index
    hips, head = idx[0], idx[CANONICAL_NAMES.index("Head")]
    if up_axis is None:
        up_axis = detect_up_axis(rest_positions, head, hips)
    if up_axis not in ("y", "z"):
        raise RigMapError(f"up axis must be 'y' or 'z', got {up_axis!r}")
    # World change to Y up: Z up (x, y, z) -> (x, z, -y) is a -90 degree turn about x.
    to_y = identity() if up_axis == "y" else quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), -np.pi / 2)
    p = rotate(to_y, rest_positions)
    left = p[idx[CANONICAL_NAMES.index("LeftUpLeg")]] - p[idx[CANONICAL_NAMES.index("RightUpLeg")]]
    # Rigs are authored facing along an axis: the turn is snapped to quarter turns so that a subject's slight
    # asymmetry does not turn the motion.
    facing = float(np.round(np.arctan2(left[2], left[0]) / (np.pi / 2)) * (np.pi / 2))
    world = quat_mul(quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), facing), to_y)
    height = float(np.ptp(rotate(world, rest_positions)[:, 1]))
    if units is None:
        units = detect_units(height)
    if units not in UNITS:
        raise RigMapError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    return world, up_axis, units, facing


#: Joint extent of a standing person (head joint to toe joints) per leg length (thigh + shin bone), as on the CMU
#: skeleton (23.9 / 14.65 units).  Units are detected from bone lengths, which no pose and no rest pose changes.
HEIGHT_PER_LEG = 1.63
#: A pose is standing if the trunk (hips to head) and both legs (hip socket to ankle) are within 30 degrees of up,
#: measured as the cosine ("uprightness") of the worst of the three.
STANDING_COS = float(np.cos(np.radians(30.0)))
_HEAD = CANONICAL_NAMES.index("Head")
_LEGS = tuple(tuple(CANONICAL_NAMES.index(f"{s}{p}") for p in ("UpLeg", "Foot")) for s in ("Left", "Right"))


def leg_length(skeleton: Skeleton, source_index: NDArray[np.intp]) -> float:
    """Mean length of the two legs (hip socket to ankle, along the bones) in the skeleton's units."""
    lengths = []
    for upleg, foot in _LEGS:
        chain = _chain(skeleton.parents, int(source_index[foot]), int(source_index[upleg]))
        lengths.append(float(sum(np.linalg.norm(skeleton.offsets[j]) for j in chain)))
    return float(np.mean(lengths))


def uprightness(positions: Array, source_index: NDArray[np.intp]) -> Array:
    """``(...)`` the cosine between up (+Y) and the least upright of trunk, left leg and right leg, for joint
    positions ``(..., J, 3)`` (Y up): 1 standing straight, 0 lying, negative upside down."""
    idx = source_index

    def up_share(v: Array) -> Array:
        return v[..., 1] / np.maximum(np.linalg.norm(v, axis=-1), 1e-12)
    trunk = up_share(positions[..., idx[_HEAD], :] - positions[..., idx[0], :])
    legs = [up_share(positions[..., idx[a], :] - positions[..., idx[b], :]) for a, b in _LEGS]
    return np.minimum(trunk, np.minimum(*legs))


def motion_up_axis(positions: Array, source_index: NDArray[np.intp]) -> str:
    """``"y"`` or ``"z"``: the axis along which the head is above the hips in most frames of ``(F, J, 3)``."""
    d = positions[:, source_index[_HEAD]] - positions[:, source_index[0]]
    d = np.median(d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12), axis=0)
    return "y" if abs(d[1]) >= abs(d[2]) else "z"


def units_from_legs(leg: float) -> str:
    """The unit in which legs of length ``leg`` (:func:`leg_length`) belong to a plausible human."""
    height = HEIGHT_PER_LEG * leg
    for unit, (_, (lo, hi)) in UNITS.items():
        if lo <= height <= hi:
            return unit
    raise RigMapError(f"legs of {leg:.4g} units (a standing height of about {height:.4g} units) are not a human "
                      f"height in m, cm, mm, inches or CMU units; give the units explicitly (--units, or the units "
                      f"field of the upload)")


@dataclass(frozen=True, eq=False)
class Normalized:
    """A source motion brought into the canonical form: ``bvh`` (CMU joints and channels, Y up, facing +Z), the
    ``mapping``, the detected or given ``units`` and ``up_axis``, ``metres_per_unit`` and ``facing_angle`` (radians
    about up that turned the source's left to +X).  ``reference_frame``: the source frame whose pose is the rest
    pose of ``bvh`` when the source's own rest (all-zero) pose is not a standing pose, else ``None``.
    ``source_positions``: ``(F, 31, 3)`` the mapped source joints by the source's own forward kinematics, turned
    into the canonical world, in source units (an unmapped joint at its canonical parent's place): what the
    fidelity gate (:mod:`anim_core.clips.fidelity`) holds the retargeted motion against."""

    bvh: Bvh
    mapping: RigMapping
    units: str
    up_axis: str
    metres_per_unit: float
    facing_angle: float
    notes: tuple[str, ...] = field(default=())
    reference_frame: int | None = None
    source_positions: Array | None = field(default=None, repr=False)


def normalize_motion(skeleton: Skeleton, rotations: Array, root_translation: Array, frame_time: float,
                     end_sites: Mapping[int, Array], source: str, explicit: Mapping[str, str] | None = None,
                     units: str | None = None, up_axis: str | None = None,
                     rest: Literal["zero", "motion"] | None = None) -> Normalized:
    """Bring a motion on any humanoid skeleton into the canonical form (see :class:`Normalized`).

    ``skeleton``: source joints (any rest rotations, any local joint frames); ``rotations``: ``(F, J, 4)`` local
    (w, x, y, z); ``root_translation``: ``(F, 3)`` in source units; ``end_sites``: leaf offsets per joint index.
    ``units`` (a key of :data:`UNITS`) and ``up_axis`` (``"y"``/``"z"``) override the detection, which reads the
    motion: up is where the head is above the hips in most frames, units follow from the leg length.

    Method: the canonical joints' global rotations are the mapped source joints' global rotations taken relative
    to a **standing reference pose** and turned to the canonical world (Y up, left at +X); the reference pose's
    joint positions become the canonical rest offsets.  The reference is the source's rest pose when that pose
    stands (head above hips, legs down, :data:`STANDING_COS`), else the most upright frame of the motion
    (``rest``: force ``"zero"`` or ``"motion"``).  So every canonical bone points where the source's bone points in
    the world at every frame, whatever the source's rest pose and local joint frames are: rigs that differ only in
    those give the same canonical motion.
    """
    rotations = np.asarray(rotations, dtype=np.float64)
    n_frames = rotations.shape[0]
    if n_frames > MAX_FRAMES:
        raise RigMapError(f"{source}: {n_frames} frames; at most {MAX_FRAMES} are supported")
    if n_frames == 0:
        raise RigMapError(f"{source}: the motion has no frames")
    if not (np.all(np.isfinite(rotations)) and np.all(np.isfinite(root_translation))):
        raise RigMapError(f"{source}: the motion holds NaN or infinite values")
    if rest not in (None, "zero", "motion"):
        raise ValueError(f"rest must be None, 'zero' or 'motion', got {rest!r}")
    if up_axis not in (None, "y", "z"):
        raise RigMapError(f"up axis must be 'y' or 'z', got {up_axis!r}")
    if units is not None and units not in UNITS:
        raise RigMapError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    g_rot, g_pos = skeleton.forward_kinematics(rotations, root_translation)
    rest_rot, rest_pos = skeleton.rest_global()

    def mapped(positions: Array | None) -> RigMapping:
        try:
            return map_skeleton(skeleton, explicit, positions)
        except RigMapError as exc:
            raise RigMapError(f"{source}: {exc}") from None

    try:
        mapping = map_skeleton(skeleton, explicit)
    except RigMapError:
        mapping = mapped(g_pos[0])  # a rest pose that is no human pose: distances measured on the motion
    idx = mapping.source_index
    if up_axis is None:
        up_axis = motion_up_axis(g_pos, idx)
    # World change to Y up: Z up (x, y, z) -> (x, z, -y) is a -90 degree turn about x.
    to_y = identity() if up_axis == "y" else quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), -np.pi / 2)
    reference: int | None = None
    if rest == "motion" or (rest is None and uprightness(rotate(to_y, rest_pos), idx) < STANDING_COS):
        reference = int(np.argmax(uprightness(rotate(to_y, g_pos), idx)))
        mapping = mapped(g_pos[reference])
        idx = mapping.source_index
        rest_rot, rest_pos = g_rot[reference], g_pos[reference]
    if units is None:
        try:
            units = units_from_legs(leg_length(skeleton, idx))
        except RigMapError as exc:
            raise RigMapError(f"{source}: {exc}") from None
    p = rotate(to_y, rest_pos)
    left = p[idx[CANONICAL_NAMES.index("LeftUpLeg")]] - p[idx[CANONICAL_NAMES.index("RightUpLeg")]]
    # Rigs are authored facing along an axis: the turn is snapped to quarter turns so that a subject's slight
    # asymmetry does not turn the motion.
    facing = float(np.round(np.arctan2(left[2], left[0]) / (np.pi / 2)) * (np.pi / 2))
    world = quat_mul(quat_from_axis_angle(np.array([0.0, 1.0, 0.0]), facing), to_y)
    p = rotate(world, rest_pos)
    hips = idx[0]

    # Source global rotation relative to the reference, in the new world: W G G_ref^-1 W^-1.
    aligned = quat_mul(quat_mul(world, quat_mul(g_rot, quat_conj(rest_rot))), quat_conj(world))
    n = len(CANONICAL_NAMES)
    c_rest = np.zeros((n, 3))
    c_glob = np.empty((n_frames, n, 4))
    for c in range(n):  # 31 canonical joints, vectorized over frames
        parent = CANONICAL_PARENTS[c]
        if idx[c] >= 0:
            c_rest[c] = p[idx[c]]
            c_glob[:, c] = aligned[:, idx[c]]
        else:
            c_rest[c] = c_rest[parent]
            c_glob[:, c] = c_glob[:, parent]
    own = np.empty((n_frames, n, 3))
    for c in range(n):
        own[:, c] = g_pos[:, idx[c]] if idx[c] >= 0 else own[:, CANONICAL_PARENTS[c]]
    own = rotate(world, own)
    offsets = c_rest.copy()
    offsets[1:] -= c_rest[CANONICAL_PARENTS[1:]]
    offsets[0] = 0.0  # the root translation is the hips' place, whatever pose the rest is
    local = c_glob.copy()
    local[:, 1:] = quat_mul(quat_conj(c_glob[:, CANONICAL_PARENTS[1:]]), c_glob[:, 1:])
    root = rotate(world, g_pos[:, hips])
    ends: dict[int, Array] = {}
    for c in range(n):
        if c in CANONICAL_PARENTS:
            continue
        j = idx[c]
        if j >= 0 and j in end_sites:
            # The End Site offset is in the joint's frame; bring it to the world at rest, then to the new world.
            ends[c] = rotate(world, rotate(rest_rot[j], np.asarray(end_sites[j], np.float64)))
        elif j >= 0 and skeleton.children(j):
            ends[c] = p[skeleton.children(j)[0]] - p[j]
        else:
            ends[c] = np.zeros(3)
    bvh = bvh_from_poses(Skeleton(CANONICAL_NAMES, CANONICAL_PARENTS, offsets), local, root, frame_time, ends,
                         source)
    notes = []
    if reference is not None:
        notes.append(f"the rest (all-zero) pose is not a standing pose: the motion is taken relative to the pose "
                     f"of frame {reference}" if rest is None else f"rest pose taken from frame {reference}")
    if abs(facing) > 1e-9:
        notes.append(f"turned {np.degrees(facing):.1f} degrees about up so the character's left is +X")
    return Normalized(bvh, mapping, units, up_axis, UNITS[units][0], facing, tuple(notes), reference, own)


def _bvh_motion(bvh: Bvh) -> tuple[Skeleton, Array, Array, dict[int, Array], list[str]]:
    """The skeleton (constant position channels folded into the offsets), local rotations ``(F, J, 4)``, root
    translation ``(F, 3)`` and End Sites of a BVH as tools write it, with notes on what was done.

    A static reference root above the joint that carries the motion's translation (the Bandai Namco and
    MotionBuilder layout: ``joint_Root`` above ``Hips``) is left out: its constant transform moves into the
    translation and rotation of the new root.  Position channels on other joints must be constant (those equal
    to the OFFSET restate the bone); animated ones that stay within 1 % of the bone's length are averaged, others
    are refused with the joint named.
    """
    s = bvh.skeleton
    names = s.names
    groups, columns = bvh._columns()
    padded = bvh._padded_motion()
    n_frames, n_joints = bvh.n_frames, s.n_joints
    rot = np.empty((n_frames, n_joints, 4))
    for order, (joints, cols) in groups.items():
        rot[:, joints] = quat_from_euler(np.radians(padded[:, cols]), order)
    has = columns >= 0  # (J, 3)
    values = padded[:, columns]  # (F, J, 3), 0 where a channel is missing
    scale = np.maximum(np.linalg.norm(s.offsets, axis=1), 1.0)
    varying = np.any(np.abs(values - values[:1]) > 1e-6 * scale[None, :, None], axis=(0, 2))  # rounding is not motion
    # Files that restate every bone in position channels (values equal to the OFFSET) mean the channel value *is*
    # the joint's translation; the moving root of such a file is placed by its channel values alone.
    restated = has.any(axis=1) & np.all(~has | (np.abs(values[0] - s.offsets) <= OFFSET_MATCH * np.maximum(
        np.abs(s.offsets), 1.0)), axis=1)
    restated[0] = False
    replace = bool(np.any(restated[1:] & ~varying[1:]))

    def translation(j: int) -> Array:  # (F, 3) joint j's translation in its parent's frame
        if j == 0:
            return s.offsets[0] + values[:, 0]
        if replace:
            return np.where(has[j], values[:, j], s.offsets[j])
        return s.offsets[j] + np.where(restated[j], 0.0, values[:, j])

    static = s.offsets + np.where(restated[:, None], 0.0, values[0])  # translation of joints with constant channels
    static[0] = s.offsets[0]
    moving = [j for j in range(1, n_joints) if varying[j]]
    children = [s.children(j) for j in range(n_joints)]
    top = 0
    if moving:
        # The joint that carries the body: the first one that translates, if everything above it is still (a
        # static reference root); else the first branching joint (the hips) below a chain of single joints whose
        # motion, whatever it is, becomes the root's.
        first = moving[0]
        ancestors = _chain(s.parents, first, -1)[:-1]
        still = [not varying[a] and np.allclose(rot[:, a], rot[:1, a], atol=1e-12) for a in ancestors]
        still[0] = still[0] and not np.any(np.abs(values[:, 0] - values[:1, 0]) > 1e-6 * scale[0])
        if all(still):
            top = first
        else:
            top = 0
            while len(children[top]) == 1:
                top = children[top][0]
    notes: list[str] = []
    for j in moving:
        if j == top or _chain(s.parents, top, j):
            continue
        mean, spread, still = still_translation(translation(j))
        if not still:
            raise RigMapError(f"{bvh.source}: joint {names[j]!r} has animated position channels (it moves up to "
                              f"{spread:.3g} units against its parent); only the body's root "
                              f"({names[top]!r}) may translate: export the motion without translation keys on "
                              f"{names[j]!r} (bake them into rotations)")
        static[j] = mean
        notes.append(f"the position channels of {names[j]!r} vary by at most {spread:.3g} units: their mean is "
                     f"used")
    if top == 0:
        skeleton = Skeleton(names, s.parents, static)
        return skeleton, rot, padded[:, columns[0]], dict(bvh.end_sites), notes
    # Re-root at ``top``: the joints above it become one transform per frame.
    q, t = identity((n_frames,)), np.zeros((n_frames, 3))
    for a in _chain(s.parents, top, -1)[:-1]:
        t = t + rotate(q, translation(a))
        q = quat_mul(q, rot[:, a])
    own = translation(top)
    keep = [top] + [j for j in range(top + 1, n_joints) if _chain(s.parents, j, top)]
    new = {j: k for k, j in enumerate(keep)}
    offsets = static[keep]
    offsets[0] = 0.0
    sub = Skeleton([names[j] for j in keep], [new.get(int(s.parents[j]), -1) for j in keep], offsets)
    rotations = rot[:, keep]
    rotations[:, 0] = quat_mul(q, rot[:, top])
    root = t + rotate(q, own)
    dropped = [names[j] for j in range(n_joints) if j not in new]
    notes.append(f"{', '.join(repr(d) for d in dropped)} above {names[top]!r} left out (its motion moved into "
                 f"{names[top]!r}, the new root)")
    return sub, rotations, root, {new[j]: e for j, e in bvh.end_sites.items() if j in new}, notes


def normalize_bvh(bvh: Bvh, explicit: Mapping[str, str] | None = None, units: str | None = None,
                  up_axis: str | None = None, rest: Literal["zero", "motion"] | None = None) -> Normalized:
    """:func:`normalize_motion` of a BVH file as tools write it (:func:`_bvh_motion`: a static reference root
    above the hips, position channels on every joint, any Euler order)."""
    if bvh.skeleton.n_joints > MAX_JOINTS:
        raise RigMapError(f"{bvh.source}: {bvh.skeleton.n_joints} joints; at most {MAX_JOINTS} are supported")
    if bvh.n_frames == 0:
        raise RigMapError(f"{bvh.source}: the MOTION section has no frames ('Frames: 0')")
    zero = [bvh.skeleton.names[j] for j in range(1, bvh.skeleton.n_joints)
            if np.linalg.norm(bvh.skeleton.offsets[j]) < 1e-12 and not bvh.skeleton.children(j)
            and np.linalg.norm(bvh.end_sites.get(j, np.zeros(3))) < 1e-12]
    skeleton, rotations, root, end_sites, read_notes = _bvh_motion(bvh)
    out = normalize_motion(skeleton, rotations, root, bvh.frame_time, end_sites, bvh.source, explicit, units,
                           up_axis, rest)
    s = bvh.skeleton
    if (s.names == CANONICAL_NAMES and np.array_equal(s.parents, CANONICAL_PARENTS) and out.up_axis == "y"
            and out.facing_angle == 0 and out.reference_frame is None
            and np.array_equal(out.mapping.source_index, np.arange(len(CANONICAL_NAMES)))):
        # Already canonical (a CMU file): the file itself, bit for bit; the computation would only add rounding.
        out = dataclasses.replace(out, bvh=bvh)
    notes = (*read_notes, *out.notes) + ((f"zero-length leaf bones ignored: {', '.join(zero)}",) if zero else ())
    return dataclasses.replace(out, notes=notes)
