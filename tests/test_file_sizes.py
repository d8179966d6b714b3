"""No source file of ``anim_core`` or ``server`` is over ``MAX_LINES`` lines, and no function over
``MAX_FUNCTION_LINES``, unless it is listed here with the reason (issue 37: a big file or function does several
jobs; split it along its seams)."""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_LINES = 600
# path -> why it is still longer; a file that shrinks below the limit must leave the list (the second test).
LONG: dict[str, str] = {}


def line_counts() -> dict[str, int]:
    """Relative path -> lines, of every Python file of ``anim_core`` and ``server``."""
    return {path.relative_to(ROOT).as_posix(): len(path.read_text(encoding="utf-8").splitlines())
            for top in ("anim_core", "server") for path in sorted((ROOT / top).rglob("*.py"))}


def test_no_file_is_over_the_limit_without_a_written_reason():
    counts = line_counts()
    assert len(counts) > 50  # the source was read
    assert {p: n for p, n in counts.items() if n > MAX_LINES and p not in LONG} == {}


def test_every_listed_file_is_still_long_and_has_a_reason():
    counts = line_counts()
    assert {p: counts.get(p) for p in LONG if counts.get(p, 0) <= MAX_LINES} == {}
    assert all(reason.strip() for reason in LONG.values())


MAX_FUNCTION_LINES = 80
# "path:qualname" -> why it is still longer (lines from ``def`` to its last line, docstring included); a function
# that shrinks to the limit must leave the list (the second test).
LONG_FUNCTIONS: dict[str, str] = {}


def _functions(node: ast.AST, prefix: str = "") -> Iterator[tuple[str, ast.FunctionDef | ast.AsyncFunctionDef]]:
    """``(qualname, node)`` of every function under ``node``, as Python names them (``Class.method``,
    ``outer.<locals>.inner``); a function defined under ``if``/``try`` keeps its enclosing scope's name."""
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
            yield prefix + child.name, child
            yield from _functions(child, f"{prefix}{child.name}.<locals>.")
        elif isinstance(child, ast.ClassDef):
            yield from _functions(child, f"{prefix}{child.name}.")
        else:
            yield from _functions(child, prefix)


def function_lengths() -> dict[str, int]:
    """``"path:qualname"`` -> lines (``def`` to its last line) of every function of ``anim_core`` and ``server``;
    the longest where one name is defined twice."""
    out: dict[str, int] = {}
    for top in ("anim_core", "server"):
        for path in sorted((ROOT / top).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for qualname, node in _functions(ast.parse(path.read_text(encoding="utf-8"), filename=rel)):
                key = f"{rel}:{qualname}"
                out[key] = max(out.get(key, 0), node.end_lineno - node.lineno + 1)  # type: ignore[operator]
    return out


def test_no_function_is_over_the_limit_without_a_written_reason():
    lengths = function_lengths()
    assert len(lengths) > 500 and lengths["anim_core/io/bvh.py:parse_bvh"] > 1  # the source was read
    assert {f: n for f, n in lengths.items() if n > MAX_FUNCTION_LINES and f not in LONG_FUNCTIONS} == {}


def test_every_listed_function_is_still_long_and_has_a_reason():
    lengths = function_lengths()
    assert {f: lengths.get(f) for f in LONG_FUNCTIONS if lengths.get(f, 0) <= MAX_FUNCTION_LINES} == {}
    assert all(reason.strip() for reason in LONG_FUNCTIONS.values())
