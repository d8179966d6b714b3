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
