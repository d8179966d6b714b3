"""The ways of animating a clip from its reference (the conditions of a study): the hybrid, the C2 spline, IK and
foot locking, key reduction and quantization, key picking; their builders (:mod:`.builders`) and the registry
that lists them in one place (:mod:`.conditions`).
"""
