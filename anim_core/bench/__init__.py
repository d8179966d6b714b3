"""The crowd-posing benchmark (:mod:`.suite`).
"""
