"""Comparing poses as a viewer sees them, for the composite tests (issue 39)."""

from __future__ import annotations

import numpy as np

from anim_core.clips.record import BuiltClip
from anim_core.math.quat import quat_conj, quat_mul


def same(a: np.ndarray, b: np.ndarray) -> float:
    """Largest ``1 - |<a, b>|`` over quaternions: 0 where the rotations are equal (q and -q alike)."""
    return float(np.abs(1.0 - np.abs(np.sum(a * b, axis=-1))).max())


def mesh_local(clip: BuiltClip, local: np.ndarray) -> np.ndarray:
    """Each bone's rotation in the mesh relative to its parent bone's, ``B_p L_j B_j^-1`` (``B``: the clip's own
    binding, ``character.bind_rotations``; the root's ``L_0 B_0^-1``): what a viewer sees of local rotations
    ``(T, J, 4)``, whichever take's skeleton they play on (each take is bound on its own; a composite plays its
    takes on its first take's skeleton)."""
    bind = clip.character.bind_rotations
    parent = bind[np.maximum(clip.character.skeleton.parents, 0)].copy()
    parent[0] = (1.0, 0.0, 0.0, 0.0)
    return quat_mul(quat_mul(parent, local), quat_conj(bind))
