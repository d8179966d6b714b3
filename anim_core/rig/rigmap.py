"""Mapping any common humanoid skeleton onto the CMU 31-joint skeleton the character is rigged for.

Conventions: the **canonical skeleton** is the CMU one (:data:`CANONICAL_NAMES`, :data:`CANONICAL_PARENTS`), Y up,
the character facing +Z with its left at +X, lengths in the source's units (``metres_per_unit`` says what they
are; :data:`UNITS` the units a source may be in).  Every other part of anim_core that takes a BVH (clips,
retargeting, foot contacts) takes it in that form, so a source from another rig is first brought into it with
:func:`anim_core.rig.normalize.normalize_bvh`, which maps its joints here.

Names are read as side + stem with candidate roles (:mod:`anim_core.rig.names`); the hierarchy and the rest-pose
bone lengths decide: a limb is the path
from the hips (legs) or the chest (arms: the joint where both arms' paths meet) to its end joint (``foot``/
``ankle``, ``hand``/``wrist``); the knee and elbow are the joints of that path that split it into two long parts,
the thigh and upper arm the joints that carry the length to them (so a ``Leg`` a few centimetres below the hip is
a helper, the knee on a ``Shin`` is the knee, and a ``Shoulder`` under a separate ``Collar`` is the upper arm).
Helper joints (twist, roll, end, ...) are never chosen for a limb.  Every decision is recorded with its reason in
:attr:`RigMapping.decisions`.

Joints of the source that map to nothing are reported (:attr:`RigMapping.unmapped`) and their rotations fold into
the nearest mapped joint below them: exact for helpers that do not rotate off the bone (twist bones, fixed
helpers), an approximation otherwise.
"""

from __future__ import annotations

import json
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..math.skeleton import Skeleton
from .names import CENTRAL_HEAD, CENTRAL_HIPS, HELPER, SideName, detect_convention, has_role, split_side
from .structure import RigMapError, common_ancestor, joint_chain, on_segment, structural_anchors

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


class _Mapper:
    def __init__(self, names: Sequence[str], parents: NDArray[np.intp], rest_positions: Array) -> None:
        self.names = tuple(names)
        self.parents = parents
        self.pos = rest_positions
        self.sides = [split_side(n) for n in names]
        self.helper = [bool(HELPER.search(s.stem)) for s in self.sides]
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
                and has_role(self.sides[j].stem, role)]

    def top(self, joints: list[int]) -> int | None:
        return min(joints, key=lambda j: (self.depth[j], j)) if joints else None

    def dist(self, a: int, b: int) -> float:
        return float(np.linalg.norm(self.pos[a] - self.pos[b]))

    def limb(self, side: str, base: int, end: int, prefix: str, kinds: tuple[str, str, str]) -> None:
        """Map a leg (``kinds`` = upleg, knee, hipjoint) or an arm (arm, elbow, collar) from ``base`` to ``end``."""
        upper_role, middle_role = kinds[:2]
        canon = {"upleg": ("UpLeg", "Leg", "HipJoint"), "arm": ("Arm", "ForeArm", "Shoulder")}[upper_role]
        path = joint_chain(self.parents, end, base)[:-1]  # joints between base and end
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
            return 0.55 <= ratio <= 2.0 and on_segment(self.pos, path, j, middle)
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
                      and self.sides[j].stem in CENTRAL_HIPS]
        feet = {s: self.top(self.named("foot", s)) for s in sides}
        hands = {s: self.top(self.named("hand", s)) for s in sides}
        if feet["L"] is not None and feet["R"] is not None:
            lca = common_ancestor(self.parents, feet["L"], feet["R"])
            hips = self.top([j for j in hips_named if j == lca or joint_chain(self.parents, lca, j)])
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
            if foot is not None and joint_chain(self.parents, foot, hips):
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
            chest = common_ancestor(self.parents, *present)
        else:  # one arm: the chest is the first branching joint above its hand
            chest = int(self.parents[present[0]])
            while chest > 0 and len([c for c in range(len(self.names)) if self.parents[c] == chest]) < 2:
                chest = int(self.parents[chest])
        if chest != hips and joint_chain(self.parents, chest, hips):
            self.set("Spine1", chest, "where the paths to both hands meet (the chest)")
            spine = [j for j in joint_chain(self.parents, chest, hips)[:-1]]
            if len(spine) >= 2:
                self.set("LowerBack", spine[0], "first spine joint above the hips")
            if spine:
                self.set("Spine", spine[-1], "last spine joint below the chest"
                         + (f"; {[self.names[j] for j in spine[1:-1]]} fold into it" if len(spine) > 2 else ""))
        else:
            chest = hips
        head = self.top([j for j in range(len(self.names)) if self.sides[j].side is None and not self.helper[j]
                         and self.sides[j].stem in CENTRAL_HEAD and joint_chain(self.parents, j, chest)])
        if head is not None:
            self.set("Head", head, f"named {self.names[head]!r}, above the chest")
            neck = joint_chain(self.parents, head, chest)[:-1]
            if len(neck) >= 2:
                self.set("Neck", neck[0], "first joint above the chest towards the head")
            if neck:
                self.set("Neck1", neck[-1], "joint below the head")
        for s, word in sides.items():
            hand = hands[s]
            if hand is None or not joint_chain(self.parents, hand, chest):
                continue
            self.set(word + "Hand", hand, f"named {self.names[hand]!r} (the highest {word.lower()} hand/wrist)")
            self.limb(s, chest, hand, word, ("arm", "elbow", "collar"))
            below = [c for c in range(hand + 1, len(self.names)) if joint_chain(self.parents, c, hand)]
            thumb = self.top(self.named("thumb", s, below))
            base = self.top(self.named("fingerbase", s, below))
            self.set(word + "FingerBase", base, "named finger base under the hand")
            if base is not None:
                below = [c for c in below if joint_chain(self.parents, c, base)]
            index = self.top(self.named("index", s, below))
            self.set(("L" if s == "L" else "R") + "Thumb", thumb, "first thumb joint under the hand")
            if index is not None:
                self.set(word + "HandIndex1", index, "first index/finger joint under the hand")


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
        if j is not None and p >= 0 and not joint_chain(skeleton.parents, j, mapper.map[CANONICAL_NAMES[p]]):
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


#: Metres per unit and the plausible range of a standing humanoid's rest-pose height (joints only) in that unit.
UNITS: dict[str, tuple[float, tuple[float, float]]] = {
    "m": (1.0, (0.9, 2.4)),
    "inch": (0.0254, (36.0, 89.9)),
    "cm": (0.01, (90.0, 240.0)),
    "mm": (0.001, (900.0, 2400.0)),
    # CMU's BVH conversions: 1 unit = (1 / 0.45) inches.
    "cmu": (0.0254 / 0.45, (15.0, 35.0)),
}
