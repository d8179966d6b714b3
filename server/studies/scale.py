"""The five-point answer scale and its scoring: defined here once, for studies, participants and statistics.

A trial shows a reference stimulus and a test stimulus side by side; ``reference_side`` says where the reference
is.  The participant's choice is stored as given; its score is from the test condition's point of view:
+2 test significantly better, +1 slightly better, 0 equal, -1 reference slightly better, -2 reference
significantly better.  (The thesis: hybrid = test, keyframe = reference.)
"""

from __future__ import annotations

from typing import Literal

Choice = Literal["left_much", "left_slightly", "equal", "right_slightly", "right_much"]
Side = Literal["left", "right"]
CHOICES: tuple[str, ...] = ("left_much", "left_slightly", "equal", "right_slightly", "right_much")
# The raw answer, left = +2 ... right = -2, whatever is shown where (used for the side bias).
CHOICE_SCORES = {"left_much": 2, "left_slightly": 1, "equal": 0, "right_slightly": -1, "right_much": -2}
SCORES = (-2, -1, 0, 1, 2)
# The thesis wording of the five answers, in the order of CHOICES.
DEFAULT_LABELS = ("Left animation is significantly better than the right animation",
                  "Left animation is slightly better than the right animation",
                  "They look equal in visual quality",
                  "Right animation is slightly better than the left animation",
                  "Right animation is significantly better than the left animation")
DEFAULT_QUESTION = "Which animation looks better?"


def other_side(side: str) -> str:
    return "right" if side == "left" else "left"


def score(choice: str, reference_side: str) -> int:
    """The answer from the test condition's point of view (see the module docstring)."""
    value = CHOICE_SCORES[choice]
    return -value if reference_side == "left" else value
