"""Which pairs a session of a design shows, by the design's mode (``design.Design.mode``): the pure part of
:mod:`server.participants.assign`, which reads the sessions and votes (adaptive designs' batches are
:func:`server.analysis.adaptive.adaptive_batches`).

``reference`` and ``all-pairs``: every test comparison of the study.  ``incomplete``: a slice of
``pairs_per_session`` pairs per animation from a fixed cyclic order of the pairs, the slice moving on by that many
with every session, so over sessions every pair is shown equally often (±1).  ``adaptive``: per animation, the
N-1 pairs picked from the votes answered before the session started (the vote log) and the session's seed, by
:func:`server.analysis.adaptive.next_batch` (``aim = "reference"``, the default) or
:func:`server.analysis.adaptive.information_tree` (``aim = "order"``).  Catch and practice comparisons are the same
in every mode.
"""

from __future__ import annotations

import random

from .design import Design
from .models import ComparisonKind, Study

PairKey = tuple[str, str, str]  # (animation, first condition, second condition)


def pair_comparisons(study: Study) -> dict[PairKey, int]:
    """(animation, first condition, second condition) -> comparison id of every test comparison of ``study``."""
    return {(c.reference.animation, c.reference.condition, c.test.condition): c.id for c in study.comparisons
            if c.kind == ComparisonKind.test}


def incomplete_pairs(design: Design, slug: str, position: int) -> list[PairKey]:
    """The pairs of the ``position``-th session (0-based) of an incomplete design: per animation a slice of
    ``pairs_per_animation()`` pairs of a cyclic order of all pairs (seeded by the study's slug and the animation,
    so animations do not share one pattern)."""
    pairs, k = design.pairs(), design.pairs_per_animation()
    out = []
    for animation in design.animations:
        order = list(pairs)
        random.Random(f"{slug}/{animation}").shuffle(order)
        out += [(animation, *order[(position * k + j) % len(order)]) for j in range(k)]
    return out
