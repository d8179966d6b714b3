"""Issue 35: the fidelity gate measures every clip a participant sees by what a viewer notices — stacked hips, a
backward knee, a foot that never lands in a stance, a mirrored half that is not the body's mirror image — and refuses
it (or marks it with ``accept_unfaithful``).  Every motion here is made from the shipped CMU walk by the test."""

import dataclasses

import numpy as np
import pytest

from anim_core.clips import fidelity
from anim_core.clips.build import AnimationConfig, ConfigError, build_animation, source_from_bvh
from anim_core.io.bvh import format_bvh, parse_bvh
from anim_core.math import contacts
from anim_core.math.clip import KeyframeClip
from anim_core.math.skeleton import Skeleton
from anim_core.methods.conditions import Condition
from anim_core.methods.hybrid import build_gait
from anim_core.rig.character import retarget
from anim_core.rig.mirror import Mirror
from anim_core.rig.normalize import normalize_bvh

CONDITIONS = (Condition.parse("keyframe", "keyframe", {}), Condition.parse("hybrid1", "hybrid", {"increment": 1}))
JOINT = {n: i for i, n in enumerate(fidelity.CANONICAL_NAMES)}


def _build(character, bvh, **config):
    out = normalize_bvh(bvh, units=config.pop("units", None))
    cfg = AnimationConfig(**{"name": "walk", "kind": "gait", "source": bvh.source, "frames": (0, bvh.n_frames - 1),
                             "playback": "loop", "in_place": True, **config})
    source = source_from_bvh(out.bvh, character, cfg, ("LHipJoint", "RHipJoint"), out.metres_per_unit,
                             out.source_positions)
    return build_animation(source, 30, CONDITIONS)


@pytest.fixture(scope="module")
def built(character, cmu_walk):
    return _build(character, cmu_walk)


def test_the_shipped_walk_passes_with_every_figure_reported(built):
    for c in built:
        assert c.fidelity.ok, (c.id, c.fidelity.problems)
        for name in ("bone_error_deg", "hip_width_ratio", "shoulder_width_ratio", "knees_forward"):
            assert c.metrics[name] is not None, (c.id, name)
    reference, hybrid = built
    assert reference.metrics["bone_error_deg"] < fidelity.BONE_LIMIT_DEG
    assert hybrid.metrics["landing_m"] < fidelity.LANDING_M
    assert hybrid.metrics["mirror_error_deg"] is not None
    assert hybrid.metrics["knees_forward"] > 0.9


def _names_shifted_by_one(bvh):
    """A Mixamo/DAZ-style naming of the CMU legs, shifted by one joint: the hip-centre joints carry the thigh names,
    the thigh heads the knee names, the knees the ankle names (a rig whose names say one thing and whose bones
    another)."""
    shift = {}
    for side, letter in (("Left", "L"), ("Right", "R")):
        shift |= {f"{letter}HipJoint": f"{side}UpLeg", f"{side}UpLeg": f"{side}Leg", f"{side}Leg": f"{side}Foot",
                  f"{side}Foot": f"{side}ToeBase", f"{side}ToeBase": f"{side}Toe_End"}
    s = bvh.skeleton
    rig = dataclasses.replace(bvh, skeleton=Skeleton([shift.get(n, n) for n in s.names], s.parents, s.offsets))
    return parse_bvh(format_bvh(rig), "shifted.bvh")


def test_thighs_from_one_point_are_refused_naming_the_mapping(character, cmu_walk):
    """Before issue 35 the gate compared the clip with the source *as mapped* (both with stacked thighs) and said
    ok."""
    with pytest.raises(ConfigError, match=r"the source's thighs start from one point \(hip width 0\.00 leg lengths\)"
                                          r": the mapping's LeftUpLeg and RightUpLeg are not the thigh heads"):
        _build(character, _names_shifted_by_one(cmu_walk), units="cmu")
    marked = _build(character, _names_shifted_by_one(cmu_walk), units="cmu", accept_unfaithful=True)
    assert all(c.metrics["unfaithful"] == 1.0 for c in marked)


def _knee_turned_back(positions: np.ndarray, side: str) -> np.ndarray:
    """The knee of one leg moved to the other side of its hip-ankle line (same thigh and shin lengths): the leg bends
    backwards; everything below the knee moves with the ankle unchanged."""
    p = positions.copy()
    hip, knee, ankle = (p[:, JOINT[f"{side}{n}"]] for n in ("UpLeg", "Leg", "Foot"))
    axis = (ankle - hip) / np.linalg.norm(ankle - hip, axis=-1, keepdims=True)
    rel = knee - hip
    along = np.sum(rel * axis, axis=-1, keepdims=True) * axis
    p[:, JOINT[f"{side}Leg"]] = hip + 2 * along - rel
    return p


def test_a_backward_knee_is_refused(built):
    reference, hybrid = built
    contact = reference.character.contact_heights
    bent = _knee_turned_back(hybrid.world_positions, "Left")
    check = fidelity.check_condition(bent, contact, reference.world_positions)
    assert any("the left knee bends backwards in 100% of the frames it is bent" in p for p in check.problems), \
        check.problems
    assert check.knees_forward < 0.1
    assert fidelity.check_condition(hybrid.world_positions, contact, reference.world_positions).ok


def test_a_foot_hovering_through_one_stance_is_refused(built):
    """The right foot lifted 8 cm in one contact phase of the reference only: it still reaches the floor elsewhere
    (the old per-clip 'feet reach' figure passed it), but it never lands in that stance."""
    reference, hybrid = built
    contact = reference.character.contact_heights
    down = contacts.foot_down(reference.world_positions[:, fidelity._FEET], 1)[:, 1]
    start, stop = max(contacts.contact_intervals(down), key=lambda r: r[1] - r[0])
    frames = np.arange(start, stop)
    lifted = hybrid.world_positions.copy()
    lifted[frames[:, None], [JOINT["RightFoot"], JOINT["RightToeBase"]], 1] += 0.08
    check = fidelity.check_condition(lifted, contact, reference.world_positions)
    assert any(p.startswith("the right foot never lands in the reference's contact") for p in check.problems), \
        check.problems
    assert check.landing_m > fidelity.LANDING_M
    assert check.foot_reach_m < fidelity.FOOT_REACH_M  # the whole-clip figure alone would not have told


def test_a_gait_mirrored_about_a_stride_is_refused(character, cmu_walk):
    """The hybrid of the walk taken relative to a stride (its most upright frame), mirrored about that rest (what the
    code did before issue 35), is refused by the mirror check; mirrored about the character's bind pose it passes."""
    out = normalize_bvh(cmu_walk, rest="motion")
    b = out.bvh
    rc = retarget(character, b.posed_skeleton(), b.end_sites)
    rot, root = b.pose_arrays()
    dt = b.frame_time
    clip = KeyframeClip(rc.skeleton, np.arange(len(rot)) * dt, rot, root * rc.root_scale, mode="clamp")
    figures = {}
    for label, bind in (("rest", None), ("bind", rc.bind_rotations)):
        hybrid = build_gait(clip, [30 * dt, 50 * dt], 70 * dt, increment=1, mirror=Mirror(rc.skeleton, bind=bind))
        t = 30 * dt + np.arange(70) * dt
        _, positions = rc.skeleton.forward_kinematics(*hybrid.sample(np.arange(70) * dt))
        _, reference = rc.skeleton.forward_kinematics(*clip.sample(t))
        figures[label] = fidelity.check_mirror(positions, reference, np.array([0, 10]), 35)
    _, problems, own = figures["rest"]
    assert own > fidelity.SELF_MIRROR_DEG and any("not the mirror image of its keyed half" in p for p in problems)
    _, problems, own = figures["bind"]
    assert own < 1.0 and not problems, problems
