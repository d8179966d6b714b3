"""Motion and character files: BVH (:mod:`.bvh`) and glTF 2.0 (:mod:`.gltf`); builds on :mod:`anim_core.math` only.
"""
