"""What every command of ``animstudy`` shares: how it fails, the argument types of the parser."""

from __future__ import annotations

import argparse
import sys

#: The frames × joints ``clips inspect`` and ``clips convert`` read at least (about 600 MB at the 300 bytes per
#: frame·joint reading takes): more than any real recording of under 20,000 frames of 100 joints, and a larger real
#: file gets more from the upload's bound (its text or binary holds every frame·joint).  A 115 KB BVH of 969
#: joints without channels asked for 9.7 million (2.6 GiB) and is refused.
CLI_FRAME_JOINTS = 2_000_000


def fail(message: str) -> int:
    print(f"error: {message}", file=sys.stderr)
    return 2


def positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 1 <= value <= 100_000:
        raise argparse.ArgumentTypeError(f"must be 1..100000, got {value}")
    return value


def even(text: str) -> int:
    value = int(text)
    if value < 16 or value % 2:
        raise argparse.ArgumentTypeError(f"video sizes must be even and at least 16, got {value}")
    return value
