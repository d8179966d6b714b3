"""Animation core: pure functions and immutable data over numpy arrays, in packages from the bottom up:
:mod:`.math` <- :mod:`.io` <- :mod:`.rig` <- :mod:`.methods` <- :mod:`.clips` / :mod:`.runtime` <- :mod:`.bench`
(each imports only packages to its left).  See docs/architecture.md.
"""
