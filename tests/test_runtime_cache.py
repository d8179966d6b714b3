"""Numba's on-disk cache of a kernel is refreshed when the kernel's own file changes, not when a function it inlines
from another file does: a kernel that calls another runtime file's compiled function would keep the old code on a
machine whose cache predates the change.  So no compiled kernel outside ``anim_core/runtime/kernels.py`` calls a
function it imports (they live in kernels.py beside what they inline: ``local_to_model``, ``ik_job``)."""

from __future__ import annotations

import ast
from pathlib import Path

RUNTIME = Path(__file__).resolve().parents[1] / "anim_core" / "runtime"


def _compiled(fn: ast.FunctionDef) -> bool:
    return any("njit" in ast.unparse(d) for d in fn.decorator_list)


def test_no_kernel_outside_kernels_py_calls_an_imported_function() -> None:
    offenders = []
    for path in sorted(RUNTIME.glob("*.py")):
        if path.name == "kernels.py":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        imported = {a.asname or a.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                    for a in node.names}
        for fn in (n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and _compiled(n)):
            calls = {c.func.id for c in ast.walk(fn) if isinstance(c, ast.Call) and isinstance(c.func, ast.Name)}
            offenders += [f"{path.name}: {fn.name} calls {name}" for name in sorted(calls & imported)]
    assert not offenders, offenders

