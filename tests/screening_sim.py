"""A simulated panel for the screening tests: export rows (``server.research.export.export_rows``'s shape) of good
observers and of planted bad ones (random, straight-lining, inverted, too fast)."""

from __future__ import annotations

from typing import Any

import numpy as np

from server.studies.scale import CHOICE_SCORES, CHOICES

ANIMATIONS = ("walk", "run", "crouch", "idle")
CONDITIONS = ("c1", "c2", "c3")
REFERENCE = "keyframe"
PLAYBACK_MS = 4000.0
# The test conditions' true quality against the reference per comparison, on the -2..+2 scale.
TRUE_QUALITY = {(a, REFERENCE, c): q for (a, c), q in zip(
    [(a, c) for a in ANIMATIONS for c in CONDITIONS],
    [-1.6, -0.6, 0.6, -1.2, 0.0, 1.2, -0.9, 0.3, 1.6, -1.9, -0.3, 0.9], strict=True)}


def choice_for(score: int, reference_side: str) -> str:
    """The choice that has ``score`` from the test condition's point of view (scale.score inverted)."""
    raw = -score if reference_side == "left" else score
    return next(c for c, v in CHOICE_SCORES.items() if v == raw)


def observer_rows(session_id: str, kind: str, rng: np.random.Generator, catch_trials: int = 2) -> list[dict[str, Any]]:
    """One participant's completed session: every comparison shown twice (sides swapped) plus catch trials.

    ``kind``: ``good`` (true quality + own bias + noise sd 0.6, rounded), ``random`` (uniform answers),
    ``straight`` (always the same raw answer), ``inverted`` (a good observer's answers negated) or ``fast`` (a good
    observer answering before the video ended)."""
    bias = rng.normal(0, 0.25)
    trials = [(key, side) for key in TRUE_QUALITY for side in ("left", "right")]
    trials += [((ANIMATIONS[i], REFERENCE, REFERENCE), "right") for i in range(catch_trials)]
    order = rng.permutation(len(trials))
    rows = []
    fixed = rng.choice(CHOICES)
    for index, t in enumerate(order):
        (animation, reference, test), side = trials[t]
        catch = test == REFERENCE
        truth = 0.0 if catch else TRUE_QUALITY[(animation, reference, test)]
        if kind == "random":
            choice = str(rng.choice(CHOICES))
        elif kind == "straight":
            choice = str(fixed)
        else:
            # the same clip on both sides is easy to see: an attentive observer strays less there
            score = int(np.clip(np.rint(truth + (0 if catch else bias) + rng.normal(0, 0.3 if catch else 0.6)),
                                -2, 2))
            if kind == "inverted" and not catch:
                score = -score
            choice = choice_for(score, side)
        raw = CHOICE_SCORES[choice]
        rt = rng.uniform(300, 900) if kind == "fast" else PLAYBACK_MS + rng.uniform(300, 6000)
        rows.append({"session_id": session_id, "trial_index": index, "practice": False, "catch": catch,
                     "animation": animation, "reference_condition": reference, "test_condition": test,
                     "reference_side": side, "test_side": "right" if side == "left" else "left", "choice": choice,
                     "score": -raw if side == "left" else raw, "rt_ms": int(rt), "session_state": "completed",
                     "outcome": "completed"})
    return rows


def panel(seed: int, good: int = 36, bad: tuple[str, ...] = ("random", "straight", "inverted", "fast")
          ) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """Rows of ``good`` good observers and one of each ``bad`` kind; session id -> kind."""
    rng = np.random.default_rng(seed)
    kinds = {f"good{i:02d}": "good" for i in range(good)} | {f"bad-{k}": k for k in bad}
    rows = [r for sid, kind in kinds.items() for r in observer_rows(sid, kind, rng)]
    return rows, kinds


PLAYBACK = {key: PLAYBACK_MS for key in [*TRUE_QUALITY, *[(a, REFERENCE, REFERENCE) for a in ANIMATIONS]]}


MEANT = {"random": "correlation", "straight": "straight_lining", "inverted": "correlation", "fast": "fast"}


def main(panels: int) -> None:
    """Every rule on ``panels`` simulated panels (seeds 0..panels-1): the seed-0 table, then how often good
    observers were flagged and bad ones missed."""
    from collections import Counter

    from server.analysis.screening import screen
    from server.studies.screening import Screening

    false_flags, missed, by_rule = Counter(), [], Counter()
    for seed in range(panels):
        rows, kinds = panel(seed)
        got = screen(rows, Screening(rules="all"), 0, PLAYBACK)
        if seed == 0:
            for sid, kind in kinds.items():
                if kind != "good":
                    print(f"seed 0  {kind:9} flagged by {', '.join(got[sid].flagged_by) or '-'}")
            good = [s for s, k in kinds.items() if k == "good" and got[s].flagged_by]
            print(f"seed 0  good      {len(good)} of 36 flagged: {[got[s].flagged_by for s in good]}")
        good = [s for s, k in kinds.items() if k == "good" and got[s].flagged_by]
        false_flags[len(good)] += 1
        by_rule.update(r for s in good for r in got[s].flagged_by)
        missed += [(seed, k) for s, k in kinds.items() if k != "good" and MEANT[k] not in got[s].flagged_by]
    print(f"{panels} panels: good observers flagged per panel {dict(sorted(false_flags.items()))}, "
          f"by rule {dict(by_rule)}; bad observers missed by their rule: {missed}")




# --- The thesis design (studies/thesis.toml): 2 conditions x 4 animations against the keyframe reference, each
# comparison once per side order, no catch trials: 16 trials per participant (issue 36).
THESIS_CONDITIONS = ("hybrid0", "hybrid1")
# Moderate true differences (-0.9 ... +1.0 on the -2..+2 scale): a good observer often answers "equal".
THESIS_QUALITY = {(a, REFERENCE, c): q for (a, c), q in zip(
    [(a, c) for a in ANIMATIONS for c in THESIS_CONDITIONS],
    [-0.9, -0.3, -0.6, 0.2, 0.4, 1.0, -0.2, 0.5], strict=True)}
THESIS_PLAYBACK = {key: PLAYBACK_MS for key in THESIS_QUALITY}
FRAME_MS = 1000 / 30


def design_rows(session_id: str, kind: str, rng: np.random.Generator,
                quality: dict[tuple[str, str, str], float] = THESIS_QUALITY) -> list[dict[str, Any]]:
    """One completed session of a design without catch trials, every comparison of ``quality`` shown twice (sides
    swapped).  Good observers: true score + own bias N(0, 0.25) + noise N(0, 0.6), rounded; they answer after one
    full playback as the page enforces, an own habit of delay (log-normal, median 1 s) after it, and the page's
    clock may end the first loop up to a frame early.  Bad kinds as :func:`observer_rows`."""
    bias = rng.normal(0, 0.25)
    habit = float(np.exp(rng.normal(np.log(1000), 1.0)))
    trials = [(key, side) for key in quality for side in ("left", "right")]
    fixed = str(rng.choice(CHOICES))
    rows = []
    for index, t in enumerate(rng.permutation(len(trials))):
        (animation, reference, test), side = trials[t]
        if kind == "random":
            choice = str(rng.choice(CHOICES))
        elif kind == "straight":
            choice = fixed
        else:
            score = int(np.clip(np.rint(quality[(animation, reference, test)] + bias + rng.normal(0, 0.6)), -2, 2))
            choice = choice_for(-score if kind == "inverted" else score, side)
        if kind == "fast":
            rt = rng.uniform(300, 900)
        else:
            rt = PLAYBACK_MS + rng.exponential(habit) - rng.uniform(0, FRAME_MS)
        raw = CHOICE_SCORES[choice]
        rows.append({"session_id": session_id, "trial_index": index, "practice": False, "catch": False,
                     "animation": animation, "reference_condition": reference, "test_condition": test,
                     "reference_side": side, "test_side": "right" if side == "left" else "left", "choice": choice,
                     "score": -raw if side == "left" else raw, "rt_ms": int(rt), "session_state": "completed",
                     "outcome": "completed"})
    return rows


def design_panel(seed: int, good: int = 36, bad: tuple[str, ...] = ("random", "straight", "inverted", "fast"),
                 quality: dict[tuple[str, str, str], float] = THESIS_QUALITY
                 ) -> tuple[list[dict[str, Any]], dict[str, str]]:
    """The issue-36 panel: ``good`` good observers and one of each ``bad`` kind in the thesis design."""
    rng = np.random.default_rng([36, seed])
    kinds = {f"good{i:02d}": "good" for i in range(good)} | {f"bad-{k}": k for k in bad}
    return [r for sid, kind in kinds.items() for r in design_rows(sid, kind, rng, quality)], kinds


def design_main(panels: int) -> None:
    """The screening of ``panels`` thesis-design panels with every rule: per rule how many good observers it
    flagged, per bad kind which rules caught it, and the panels with at most one good observer flagged."""
    import time
    from collections import Counter

    from server.analysis.screening import screen
    from server.studies.screening import Screening

    good_by_rule, bad_by_rule, caught, at_most_one = Counter(), Counter(), Counter(), 0
    too_little: Counter = Counter()
    start = time.perf_counter()
    for seed in range(panels):
        rows, kinds = design_panel(seed)
        got = screen(rows, Screening(rules="all"), 0, THESIS_PLAYBACK)
        good = [s for s, k in kinds.items() if k == "good" and got[s].flagged_by]
        at_most_one += len(good) <= 1
        good_by_rule.update(r for s in good for r in got[s].flagged_by)
        for s, k in kinds.items():
            if k != "good":
                caught[k] += bool(got[s].flagged_by)
                bad_by_rule.update((k, r) for r in got[s].flagged_by)
        first = next(iter(got.values()))
        too_little.update(r for r, v in first.results.items() if getattr(v, "judged", True) is False)
    print(f"{panels} thesis-design panels ({time.perf_counter() - start:.1f} s): <= 1 good flagged in {at_most_one}; "
          f"good observers flagged per rule (sum over panels) {dict(good_by_rule)}; bad caught (any rule) "
          f"{dict(caught)}; by rule {dict(sorted(bad_by_rule.items()))}; panels with a rule judged 'too little "
          f"data' {dict(too_little)}")


if __name__ == "__main__":
    import sys

    count = int(sys.argv[1]) if len(sys.argv) > 1 else 100
    design_main(count) if "--thesis" in sys.argv else main(count)
