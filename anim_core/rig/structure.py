"""The structure of a skeleton, whatever its joints are called: chains of joints through the tree, and the
anchors (hips, chest, legs, arms, head) found from the tree and the rest pose alone (:func:`structural_anchors`),
what :mod:`anim_core.rig.rigmap` maps a skeleton without telling names by.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


class RigMapError(ValueError):
    """A skeleton that cannot be mapped onto the character (missing parts, inconsistent explicit mapping).  Every
    module of the rig mapping raises it; it is defined here, in the lowest of them."""


def joint_chain(parents: NDArray[np.intp], j: int, stop: int) -> list[int]:
    """Joints from ``stop`` (exclusive) down to ``j`` (inclusive); empty if ``stop`` is not an ancestor."""
    out = []
    while j != stop:
        if j < 0:
            return []
        out.append(j)
        j = int(parents[j])
    return out[::-1]


def common_ancestor(parents: NDArray[np.intp], a: int, b: int) -> int:
    ancestors = set()
    while a >= 0:
        ancestors.add(a)
        a = int(parents[a])
    while b not in ancestors:
        b = int(parents[b])
    return b


def on_segment(pos: Array, path: list[int], a: int, b: int, tolerance: float = 0.05) -> bool:
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
    return joint_chain(parents, tip, base)


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
    hips, chest, hip_branches, spine, arm_branches = _hips_and_chest(parents, children, below, pos, size)
    up = pos[chest] - pos[hips]
    if np.linalg.norm(up) < 1e-12:
        raise RigMapError(f"the hips (joint {hips}) and the chest (joint {chest}) are at one place: no up")
    up /= np.linalg.norm(up)
    lateral = [float(np.linalg.norm(_across(pos[below[c]] - pos[chest], up), axis=1).max()) for c in arm_branches]
    order = np.argsort(lateral)
    if lateral[order[0]] > 0.5 * lateral[order[1]]:
        raise RigMapError(f"of the chest's (joint {chest}) branches none keeps clearly closer to the spine's line "
                          f"than the others (reach across {', '.join(f'{x:.3g}' for x in lateral)}): the neck is "
                          f"not told from the arms")
    neck = arm_branches[int(order[0])]
    arms = [c for c in arm_branches if c != neck]
    legs = [c for c in hip_branches if c != spine]
    feet = [_foot(_main_chain(parents, below[c], pos, hips), pos, hips, up) for c in legs]
    hands = [_end_of_chain(_main_chain(parents, below[c], pos, chest), children, pos, 0.5) for c in arms]
    head = _end_of_chain(_main_chain(parents, below[neck], pos, chest), children, pos, 0.0)
    left, sockets, shoulders = _facing_left(parents, below, pos, hips, chest, head, legs, arms, size)
    elbows = [_elbow(parents, pos, chest, h) for h in hands]
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


def _across(v: Array, up: Array) -> Array:
    """``v`` ``(..., 3)`` with its part along the unit ``up`` taken out."""
    return v - (v @ up)[..., None] * up


def _hips_and_chest(parents: NDArray[np.intp], children: list[list[int]], below: list[list[int]], pos: Array,
                    size: float) -> tuple[int, int, list[int], int, list[int]]:
    """``(hips, chest, the hips' three branches, the spine's branch of them, the chest's three branches)``: the
    highest joint with three branches and the highest such joint of its one branch that holds another."""
    n = len(parents)
    three = [j for j in range(n) if len(_branches(children, below, pos, j, size)) >= 3]
    if not three:
        raise RigMapError("no joint has three branches (two legs and a spine): not a humanoid tree")
    depth = np.array([len(joint_chain(parents, j, -1)) for j in range(n)])
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
    return hips, chest, hip_branches, spines[0], arm_branches


def _foot(chain: list[int], pos: Array, hips: int, up: Array) -> int:
    """The foot on a leg's ``chain`` (hips to its farthest joint): the joint below half the leg's drop from which
    the bone goes more across than down (to the toes), else the chain's last joint."""
    height = (pos[chain] - pos[hips]) @ up
    for k in range(len(chain) - 1):
        d = pos[chain[k + 1]] - pos[chain[k]]
        if height[k] < 0.5 * height.min() and abs(d @ up) < np.linalg.norm(_across(d, up)):
            return chain[k]
    return chain[-1]


def _facing_left(parents: NDArray[np.intp], below: list[list[int]], pos: Array, hips: int, chest: int, head: int,
                 legs: list[int], arms: list[int], size: float) -> tuple[Array, list[int], list[int]]:
    """``(left (3,), the legs' sockets, the shoulders)``: the legs' sockets and the shoulders stand in front of the
    spine, so forward is from the spine to them and left is up × forward."""
    # Up now from the hips to the head (closer to the vertical than the chest, which sits back), and each compared
    # with the spine joint at its height, so that little of a height difference leaks into "forward" through a
    # leaning trunk.
    up = pos[head] - pos[hips]
    up /= max(float(np.linalg.norm(up)), 1e-12)

    # Each the chain's first joint if none qualifies (only on geometry far from a body, as heavy noise makes).
    def socket(branch: int) -> int:  # the last joint of the leg at the hips' level (a quarter of its drop)
        chain = _main_chain(parents, below[branch], pos, hips)
        height = (pos[chain] - pos[hips]) @ up
        return chain[int(np.flatnonzero(height >= 0.25 * height.min()).max(initial=0))]

    def shoulder(branch: int) -> int:  # the last joint of the arm within a third of its reach across the trunk
        chain = _main_chain(parents, below[branch], pos, chest)
        far = np.linalg.norm(_across(pos[chain] - pos[chest], up), axis=1)
        return chain[int(np.flatnonzero(far <= far.max() / 3).max(initial=0))]
    sockets = [socket(c) for c in legs]
    shoulders = [shoulder(c) for c in arms]
    spine = joint_chain(parents, chest, hips)
    low_back = spine[0] if len(spine) > 1 else hips
    forward = (_across(pos[sockets].mean(axis=0) - pos[low_back], up)
               + _across(pos[shoulders].mean(axis=0) - pos[chest], up))
    if np.linalg.norm(forward) < FACING_MIN * size:
        raise RigMapError(f"the legs' sockets and the shoulders stand {np.linalg.norm(forward):.3g} units in front "
                          f"of the spine, less than {FACING_MIN:.0%} of the figure's size: left and right cannot be "
                          f"told from the geometry")
    return np.cross(up, forward / np.linalg.norm(forward)), sockets, shoulders


def _elbow(parents: NDArray[np.intp], pos: Array, chest: int, hand: int) -> int | None:
    """The elbow: within the straight stretch of the arm that ends at the hand (upper arm and forearm; the collar
    bone leaves it), the joint that splits it into the two longest parts.  Lengths alone do not tell: CMU's
    forearm is shorter than its collar bone."""
    chain = joint_chain(parents, hand, chest)
    for a in chain[:-2]:
        if on_segment(pos, chain, a, hand):
            inner = chain[chain.index(a) + 1:-1]
            return max(inner, key=lambda j: min(np.linalg.norm(pos[j] - pos[a]),
                                                np.linalg.norm(pos[hand] - pos[j])))
    return None
