"""The five-point answer scale and its scoring: defined here once, for studies, participants and statistics.

A trial shows a reference stimulus and a test stimulus side by side; ``reference_side`` says where the reference
is.  The participant's choice is stored as given; its score is from the test condition's point of view:
+2 test significantly better, +1 slightly better, 0 equal, -1 reference slightly better, -2 reference
significantly better.  (The thesis: hybrid = test, keyframe = reference.)
"""

from __future__ import annotations

from typing import Any, Literal, get_args

#: The answers' ids, from the left animation much better to the right one much better (the only place they are
#: spelled; the participant page's form sends them).
Choice = Literal["left_much", "left_slightly", "equal", "right_slightly", "right_much"]
Side = Literal["left", "right"]
CHOICES: tuple[str, ...] = get_args(Choice)
#: The strongest preference either way: scores run from -MAX_SCORE to +MAX_SCORE.
MAX_SCORE = (len(CHOICES) - 1) // 2
SCORES = tuple(range(-MAX_SCORE, MAX_SCORE + 1))
# The raw answer, left = +MAX_SCORE ... right = -MAX_SCORE, whatever is shown where (used for the side bias).
CHOICE_SCORES = dict(zip(CHOICES, reversed(SCORES), strict=True))
# The thesis wording of the five answers, in the order of CHOICES.
DEFAULT_LABELS = ("Left animation is significantly better than the right animation",
                  "Left animation is slightly better than the right animation",
                  "They look equal in visual quality",
                  "Right animation is slightly better than the left animation",
                  "Right animation is significantly better than the left animation")
DEFAULT_QUESTION = "Which animation looks better?"


def describe() -> dict[str, Any]:
    """The scale as the API gives it (the dashboard draws its axes and legends from it)."""
    return {"choices": list(CHOICES), "scores": list(SCORES), "min": -MAX_SCORE, "max": MAX_SCORE,
            "choice_scores": CHOICE_SCORES}


def other_side(side: str) -> str:
    return "right" if side == "left" else "left"


def score(choice: str, reference_side: str) -> int:
    """The answer from the test condition's point of view (see the module docstring)."""
    value = CHOICE_SCORES[choice]
    return -value if reference_side == "left" else value


# --- Answer formats (issue 38) ------------------------------------------------------------------------------
#: ``[scale] format``: ``rating5`` is the five-point scale above; ``2afc`` asks which side is the original (or
#: which moves more smoothly), ``same_different`` whether the two sides differ.
AnswerFormat = Literal["rating5", "2afc", "same_different"]
FORMATS: tuple[str, ...] = get_args(AnswerFormat)
#: Every format's answer ids, in the order the page shows them (keys 1..n): the only place they are spelled.
FORMAT_CHOICES: dict[str, tuple[str, ...]] = {
    "rating5": CHOICES,
    "2afc": ("left", "right"),
    "same_different": ("same", "different"),
}
#: Every answer id of every format (the vote's ``choice`` column holds one of them).
ALL_CHOICES: tuple[str, ...] = tuple(dict.fromkeys(c for ids in FORMAT_CHOICES.values() for c in ids))
AnyChoice = Literal["left_much", "left_slightly", "equal", "right_slightly", "right_much", "left", "right", "same",
                    "different"]
#: The English defaults of each format's question and labels (a study in another language writes its own).
FORMAT_DEFAULTS: dict[str, tuple[str, tuple[str, ...]]] = {
    "rating5": (DEFAULT_QUESTION, DEFAULT_LABELS),
    "2afc": ("Which one is the original?", ("The left one", "The right one")),
    "same_different": ("Are the two animations the same or different?", ("Same", "Different")),
}


def format_choices(answer_format: str) -> tuple[str, ...]:
    return FORMAT_CHOICES[answer_format]


def format_score(answer_format: str, choice: str, reference_side: str) -> int:
    """The stored score of an answer, from the test condition's point of view in every format: the five-point
    scale as :func:`score`; 2AFC +1 if the test side was chosen (taken for the original / the smoother), -1 if the
    reference's; same/different 0 for "same", -1 for "different" (the test was told apart)."""
    if answer_format == "rating5":
        return score(choice, reference_side)
    if answer_format == "2afc":
        return -1 if choice == reference_side else 1
    return 0 if choice == "same" else -1


def correct(answer_format: str, choice: str, reference_side: str, same_clip: bool) -> bool | None:
    """Whether an answer is right, derived (never stored): 2AFC chose the reference's side (none is right when
    both sides show one clip); same/different said "same" exactly when both sides show one clip.  None for
    ratings."""
    if answer_format == "2afc":
        return None if same_clip else choice == reference_side
    if answer_format == "same_different":
        return (choice == "same") == same_clip
    return None


def detected(answer_format: str, choice: str, reference_side: str) -> bool:
    """Whether the participant told the test from the reference (what a staircase and a psychometric fit count):
    2AFC the reference's side chosen, same/different "different"."""
    if answer_format == "2afc":
        return choice == reference_side
    return choice == "different"


def catch_failed(answer_format: str, choice: str) -> bool:
    """A failed catch trial (both sides the same clip): the strongest preference on the five-point scale,
    "different" for same/different.  A 2AFC catch trial has no wrong answer (the staircase's catch trials are
    checked by :func:`correct` on the ladder's easiest level instead)."""
    if answer_format == "rating5":
        return abs(CHOICE_SCORES[choice]) == MAX_SCORE
    if answer_format == "same_different":
        return choice == "different"
    return False


assert set(get_args(AnyChoice)) == set(ALL_CHOICES), "AnyChoice must list every format's ids"


def catch_row_failed(row: dict[str, Any]) -> bool:
    """Whether an export row of a catch trial is a failure: the same clip on both sides (test condition = reference
    condition) judged by :func:`catch_failed`; a ladder's catch trial (its easiest level) answered wrongly."""
    answer_format = row.get("answer_format") or "rating5"
    if row["test_condition"] == row["reference_condition"]:
        return catch_failed(answer_format, row["choice"])
    return row.get("correct") is False


def public(stored: dict[str, Any]) -> dict[str, Any]:
    """A study's ``[scale]`` as the participant page reads it: its format (``rating5`` for scales stored before
    formats existed) and that format's answer ids (``choices``, in the order of ``labels``), so the page never
    spells an id itself."""
    answer_format = stored.get("format", "rating5")
    return {**stored, "format": answer_format, "choices": list(format_choices(answer_format))}


#: The raw answer of every format's ids from the left side's point of view, whatever is shown where (the side bias
#: and the screening rules read it): the five-point scale's CHOICE_SCORES, 2AFC left +1 / right -1, same/different 0.
RAW_SCORES: dict[str, int] = {**CHOICE_SCORES, "left": 1, "right": -1, "same": 0, "different": 0}
