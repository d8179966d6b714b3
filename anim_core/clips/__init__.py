"""Clip sets: building every animation in every condition (:mod:`.build`), measuring the clips (:mod:`.measure`,
:mod:`.metrics`) and inspecting motion sources (:mod:`.sources`).
"""
