"""Quaternions (w, x, y, z), skeletons and forward kinematics, keyframe clips and their playback, skinning, foot
contacts: pure functions and immutable data over numpy arrays; imports nothing else of anim_core.
"""
