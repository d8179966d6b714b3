"""Rigs: joint-name mapping and normalisation of any skeleton (:mod:`.rigmap`), the study's character and
retargeting onto it (:mod:`.character`, :mod:`.gltf_character`), left/right mirroring (:mod:`.mirror`).
"""
