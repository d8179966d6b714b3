"""Issue 35: a gait's mirrored half is made about the character's bind pose (left/right symmetric by construction),
so it does not depend on the rest pose or joint frames of the rig the motion came on.  Every rig here is made from
the real CMU walk by the test itself (:func:`tests.test_wild_motion.wild_rig`): the same world motion on another
rest pose (the most upright frame of the motion, a stride with the hips turned 4.7 degrees) and other joint
frames."""


import numpy as np
import pytest

from anim_core.io.bvh import Bvh, format_bvh, parse_bvh
from anim_core.math.clip import KeyframeClip
from anim_core.math.quat import quat_from_axis_angle, rotate
from anim_core.math.skeleton import Skeleton
from anim_core.methods.hybrid import build_gait
from anim_core.rig.character import retarget
from anim_core.rig.mirror import Mirror
from anim_core.rig.rigmap import Normalized, normalize_bvh

from .test_wild_motion import wild_rig

Y = np.array([0.0, 1.0, 0.0])
#: Bones of the canonical skeleton that start at a joint the character hangs its own pelvis geometry off (the CMU
#: pelvis bones, hip centre -> thigh head).  Their direction is bound in the parent's rest frame
#: (docs/motion-from-the-wild.md): a rest pose whose pelvis is turned moves them, and the mirror doubles that turn.
PELVIS = ("LeftUpLeg", "RightUpLeg")


def _hybrid_bone_directions(character, out: Normalized, bind: bool, keys_only: slice | None = None
                            ) -> tuple[np.ndarray, list[str]]:
    """World bone directions ``(T, B, 3)`` of the hybrid (increment 1) of one gait cycle of ``out`` on the character,
    turned back by the normalisation's facing turn; the bones that have a length in the CMU file, by end joint."""
    b = out.bvh
    rc = retarget(character, b.posed_skeleton(), b.end_sites)
    rot, root = b.pose_arrays()
    dt = b.frame_time
    clip = KeyframeClip(rc.skeleton, np.arange(len(rot)) * dt, rot, root * rc.root_scale, mode="clamp")
    mirror = Mirror(rc.skeleton, bind=rc.bind_rotations if bind else None)
    hybrid = build_gait(clip, [30 * dt, 50 * dt], 70 * dt, increment=1, mirror=mirror)
    frames = np.arange(70) * dt if keys_only is None else hybrid.key_times[keys_only]
    _, p = rc.skeleton.forward_kinematics(*hybrid.sample(frames))
    p = rotate(quat_from_axis_angle(Y, -out.facing_angle), p)
    sk = rc.skeleton
    directed = [j for j in range(1, sk.n_joints) if np.linalg.norm(b.skeleton.offsets[j]) > 1e-9]
    v = p[:, directed] - p[:, sk.parents[directed]]
    return v / np.linalg.norm(v, axis=-1, keepdims=True), [sk.names[j] for j in directed]


def _with_helper_joints(rig: Bvh, helpers: list[tuple[str, str]]) -> Bvh:
    """``rig`` with still leaf joints (helper joints as DAZ and Mixamo-style rigs carry: ``lShin``, ``lCollar``) added
    right under the named parents (depth-first order kept), 3 rotation channels at 0."""
    s = rig.skeleton
    columns = np.split(rig.motion, np.cumsum([len(c) for c in rig.channels])[:-1], axis=1)
    rows = []  # name, parent name, offset, channels, columns
    for j, name in enumerate(s.names):
        rows.append((name, s.names[s.parents[j]] if s.parents[j] >= 0 else None, s.offsets[j], rig.channels[j],
                     columns[j]))
        rows += [(h, name, np.array([0.0, 3.0, 1.0]), ("Zrotation", "Xrotation", "Yrotation"),
                  np.zeros((rig.n_frames, 3))) for h, parent in helpers if parent == name]
    names = [r[0] for r in rows]
    out = Bvh(Skeleton(names, [names.index(r[1]) if r[1] else -1 for r in rows], np.array([r[2] for r in rows])),
              tuple(r[3] for r in rows), {names.index(s.names[j]): e for j, e in rig.end_sites.items()},
              rig.frame_time, np.concatenate([r[4] for r in rows], axis=1), "helpers.bvh")
    return parse_bvh(format_bvh(out), "helpers.bvh")


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # arctan2 of the cross and dot products: arccos of a dot product near 1 loses half the digits
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))).max(axis=0)


MIRRORED = slice(4, 8)  # increment 1: keys 0..3 from the mocap, 4..7 their mirror images


@pytest.mark.parametrize("bind", [True, False], ids=["about the bind pose", "about the rig's rest"])
def test_the_mirrored_keys_do_not_depend_on_the_rig_the_motion_came_on(character, cmu_walk, rng, bind):
    """The CMU walk with its T-pose as rest, taken relative to its most upright frame (a stride: the hips turned 4.7
    degrees), on a rig with bones along X and a lying zero pose, and on that rig with helper joints: mirrored about
    the character's bind pose, every bone of every mirrored key points the same way to 1e-6 degrees, but the two
    pelvis bones (under 10 degrees:
    twice the rest frame's pelvis turn, geometry the character hangs off zero-length CMU bones).  Mirrored about the
    rig's rest (what the code did before) the feet and hands are 30-70 degrees off."""
    plain, names = _hybrid_bone_directions(character, normalize_bvh(cmu_walk), bind, MIRRORED)
    pelvis = [names.index(n) for n in PELVIS]
    others = [k for k in range(len(names)) if k not in pelvis]
    lying = wild_rig(cmu_walk, rng, "x-bones", scale=100 * 0.0254 / 0.45)
    helpers = [("lShin", "LeftLeg"), ("rShin", "RightLeg"), ("lCollar", "Spine1"), ("rCollar", "Spine1")]
    for out in (normalize_bvh(cmu_walk, rest="motion"), normalize_bvh(lying),
                normalize_bvh(_with_helper_joints(lying, helpers))):
        assert out.reference_frame == 110
        diff = _angles(_hybrid_bone_directions(character, out, bind, MIRRORED)[0], plain)
        if bind:
            assert diff[others].max() < 1e-6, dict(zip(names, diff.round(4), strict=True))
            assert diff[pelvis].max() < 10.0
        else:
            assert diff[others].max() > 30.0


def test_between_the_keys_the_rigs_differ_by_the_twist_their_rest_pose_gives(character, cmu_walk, rng):
    """Between the keys SQUAD interpolates rotations, and how a bone with one child is twisted about itself in the
    bind is the rig's rest pose's (a shortest arc from it): the mirrored keys' twists differ between the rigs, and so
    do the interpolated directions, by under 3 degrees on this walk (the rig's-rest mirror: up to 68)."""
    plain, names = _hybrid_bone_directions(character, normalize_bvh(cmu_walk), True)
    pelvis = [names.index(n) for n in PELVIS]
    others = [k for k in range(len(names)) if k not in pelvis]
    diff = _angles(_hybrid_bone_directions(character, normalize_bvh(cmu_walk, rest="motion"), True)[0], plain)
    assert diff[others].max() < 3.0, dict(zip(names, diff.round(2), strict=True))
