"""Rigs: joint names (:mod:`.names`), the structure of an unnamed skeleton (:mod:`.structure`), mapping onto the
canonical joints (:mod:`.rigmap`) and normalisation of any motion (:mod:`.normalize`), the study's character and
retargeting onto it (:mod:`.character`, :mod:`.gltf_character`), left/right mirroring (:mod:`.mirror`).
"""
