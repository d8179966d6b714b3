"""Posing crowds at run time: the runtime of every kind of clip (:mod:`anim_core.runtime.core`) and the uniform
pose tables they start from (:mod:`anim_core.runtime.crowd`).  Callers import from this package.
"""

from .core import (
    BONE_LODS,
    C2_TOLERANCE_DEG,
    FIT_TOLERANCE_DEG,
    FOOT_LOCK_TOLERANCE_DEG,
    AnyRuntime,
    C2Runtime,
    FootLockRuntime,
    QuantizedRuntime,
    SplineRuntime,
    SpringRuntime,
    TableRuntime,
    angle_error_deg,
    bone_lod_mask,
    c2_runtime,
    check_inputs,
    crouch_params,
    exact_global,
    foot_lock_runtime,
    lod_pose,
    max_error_deg,
    period,
    pose_crowd,
    quantized_runtime,
    runtime_for,
    sample_times,
    spline_runtime,
    spring_runtime,
)
from .crowd import numba

if numba is not None:  # compiled only where numba is present
    from .core import crouch_path_parameter  # noqa: F401

__all__ = [
    "BONE_LODS", "C2_TOLERANCE_DEG", "FIT_TOLERANCE_DEG", "FOOT_LOCK_TOLERANCE_DEG", "AnyRuntime", "C2Runtime",
    "FootLockRuntime", "QuantizedRuntime", "SplineRuntime", "SpringRuntime", "TableRuntime", "angle_error_deg",
    "bone_lod_mask", "c2_runtime", "check_inputs", "crouch_params", "exact_global", "foot_lock_runtime", "lod_pose",
    "max_error_deg", "period", "pose_crowd", "quantized_runtime", "runtime_for", "sample_times", "spline_runtime",
    "spring_runtime",
]
