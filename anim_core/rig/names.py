"""Joint names read as side + stem, the roles a stem suggests and the naming conventions of common rigs.

Names are read as *side* + *stem* (:func:`split_side`): prefixes of Mixamo (``mixamorig:``, ``mixamorig_``,
``Armature_mixamorig``), Blender's ``DEF-``, 3ds Max's ``Bip01 `` and any ``namespace:``/``Armature|`` are dropped,
then a side is recognised as a word
(``Left``/``Right`` before or after the stem, any case), ``L_``/``R_``/``L `` prefixes, ``.L``/``_L``/``_l`` suffixes
(Blender, Unreal's ``thigh_l``), or a single letter glued to a capitalised stem (CMU's ``LHipJoint``, Poser/DAZ's
``lThigh``).  Stems give candidate roles (:data:`ROLE_STEMS`, :func:`has_role`); which joint takes a role is
decided from the hierarchy by :mod:`anim_core.rig.rigmap`.  Joints named ``twist``, ``roll``, ``helper``,
``corrective``, ``end``/``nub`` (:data:`HELPER`) are never chosen for a limb.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

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
HELPER = re.compile(r"twist|roll|helper|corrective|adj|nub|end$|site|ik|pole|target", re.IGNORECASE)


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

ROLE_STEMS: dict[str, tuple[str, ...]] = {
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
CENTRAL_HIPS = ("hips", "hip", "pelvis")
CENTRAL_HEAD = ("head",)


def has_role(stem: str, role: str) -> bool:
    base = re.sub(r"\d+$", "", stem)
    return stem in ROLE_STEMS[role] or base in ROLE_STEMS[role]


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
