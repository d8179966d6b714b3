"""Clip sets: building every animation in every condition (:mod:`.build`; an animation's entry and mocap
:mod:`.entry`, its reference clip :mod:`.reference`), measuring the clips (:mod:`.measure`, :mod:`.metrics`) and
inspecting motion sources (:mod:`.sources`).
"""
