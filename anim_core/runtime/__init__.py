"""Posing crowds at run time, ozz-style runtime and offline apart.  Callers import from this package.

* :mod:`.kinds`: the runtime of every kind of clip (what it holds, how it is posed), :func:`pose_crowd`;
* :mod:`.kernels`: their compiled kernels, one per kind, made serial and parallel by one factory;
* :mod:`.offline`: building a runtime from a clip (:func:`runtime_for`), the fits and their tolerances;
* :mod:`.checks`: accuracy: the exact curve, a pose under a LOD, the angle between them;
* :mod:`.held`: the held-update path (:class:`HeldCrowd`): a character posed at its clip's update rate only;
* :mod:`.crowd`: the uniform pose tables (and baking a hybrid into one) the table runtime starts from;
* :mod:`.blending`: the sampling, blending, additive and local-to-model jobs (ozz-style, one job per stage);
* :mod:`.ik`: the two-bone IK job (:class:`~anim_core.runtime.ik.TwoBoneIKJob`) that holds feet after a blend.
"""

from .checks import (
    angle_error_deg,
    exact_global,
    lod_pose,
    max_error_deg,
    period,
    sample_times,
)
from .crowd import numba
from .held import HeldCrowd, HeldRuntime
from .kinds import (
    BONE_LODS,
    AnyRuntime,
    C2Runtime,
    FootLockRuntime,
    QuantizedRuntime,
    SplineRuntime,
    SpringRuntime,
    TableRuntime,
    animated_joints,
    bone_lod_mask,
    check_inputs,
    pose_crowd,
    pose_threads,
)
from .offline import (
    C2_TOLERANCE_DEG,
    FIT_TOLERANCE_DEG,
    FOOT_LOCK_TOLERANCE_DEG,
    c2_runtime,
    crouch_params,
    foot_lock_runtime,
    quantized_runtime,
    runtime_for,
    spline_runtime,
    spring_runtime,
)

if numba is not None:  # compiled only where numba is present
    from .kernels import crouch_path_parameter  # noqa: F401

__all__ = [
    "BONE_LODS", "C2_TOLERANCE_DEG", "FIT_TOLERANCE_DEG", "FOOT_LOCK_TOLERANCE_DEG", "AnyRuntime", "C2Runtime",
    "FootLockRuntime", "HeldCrowd", "HeldRuntime", "QuantizedRuntime", "SplineRuntime", "SpringRuntime", "TableRuntime",
    "angle_error_deg", "animated_joints",
    "bone_lod_mask", "c2_runtime", "check_inputs", "crouch_params", "exact_global", "foot_lock_runtime", "lod_pose",
    "max_error_deg", "period", "pose_crowd", "pose_threads", "quantized_runtime", "runtime_for", "sample_times",
    "spline_runtime", "spring_runtime",
]
