"""``animstudy`` command line: the parser (:mod:`.parser`) and one module per group of commands."""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

from server.config import Settings

from .parser import build_parser, loadtest_parser

__all__ = ["build_parser", "loadtest_parser", "main"]


def _main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Each group's module is imported when its command runs: a command loads what it uses, and no more.
    if args.command == "loadtest":
        from server import loadtest

        return loadtest.main(args)
    settings = Settings.from_env()
    if args.command == "bench":
        from . import bench

        return bench.run(settings, args)
    if args.command in ("serve", "researcher"):
        from . import serve

        return serve.run(settings, args)
    if args.command in ("study", "gc", "render"):
        from . import study

        return study.run(settings, args)
    from . import clips

    return clips.run(settings, args)


def main(argv: Sequence[str] | None = None) -> int:
    try:
        return _main(argv)
    except BrokenPipeError:
        # The reader went away (`animstudy inspect | head`): not an error of ours.  Python would otherwise report
        # the broken pipe again when it flushes stdout at exit (the recipe of the signal module's docs).
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
