"""The packages of ``server`` and ``anim_core`` import each other in one direction only (docs/architecture.md): read
from the import statements of the source, lazy imports inside functions included."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def package_imports(top: str) -> dict[str, set[str]]:
    """Package (``server.studies``; a top-level module such as ``server.cli`` counts as one) -> the other packages
    of ``top`` it imports."""
    graph: dict[str, set[str]] = {}
    for path in sorted((ROOT / top).rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        module = parts[:-1] if parts[-1] == "__init__" else parts
        package = ".".join(module[:2])
        targets = graph.setdefault(package, set())
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                here = parts[:-1]  # the folder a relative import starts from
                base = here[:len(here) - node.level + 1] if node.level else ()
                name = ".".join([*base, *([node.module] if node.module else [])])
                names = [name, *(f"{name}.{a.name}" for a in node.names)]  # `from server import cli` too
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                if name.split(".")[0] == top and len(name.split(".")) > 1:
                    targets.add(".".join(name.split(".")[:2]))
        targets.discard(package)
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every package that reaches itself, with the way back (one path per package)."""
    found = []
    for start in sorted(graph):
        stack, seen = [(start, [start])], set()
        while stack:
            node, path = stack.pop()
            for nxt in sorted(graph.get(node, ())):
                if nxt == start:
                    found.append([*path, start])
                    stack = []
                    break
                if nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, [*path, nxt]))
    return found


@pytest.mark.parametrize("top", ["server", "anim_core"])
def test_no_package_imports_one_that_imports_it_back(top):
    graph = package_imports(top)
    assert len(graph) > 5  # the source was read
    assert circles(graph) == []


def test_the_study_definition_knows_nothing_of_participants_research_or_uploads():
    assert package_imports("server")["server.studies"].isdisjoint(
        {"server.participants", "server.research", "server.uploads"})


def test_the_job_system_knows_no_kind_of_job():
    """The runner runs what a kind is registered with (server.pipeline.jobs.KINDS): `jobs` imports none of the
    packages whose work its jobs do, so `uploads` can ask it whether a build runs without a circle."""
    assert package_imports("server")["server.jobs"].isdisjoint(
        {"server.pipeline", "server.uploads", "server.media", "server.clipset", "server.participants",
         "server.research", "server.cli"})


def test_uploads_only_store_files():
    """The build of uploads is a kind of job (server.pipeline): `uploads` never imports the pipeline."""
    assert package_imports("server")["server.uploads"].isdisjoint({"server.pipeline", "server.media"})


def test_the_study_definition_knows_nothing_of_the_analysis():
    assert "server.analysis" not in package_imports("server")["server.studies"]


def test_the_analysis_imports_only_the_study_definition():
    # the pure statistics read the answer scale, the design and the [screening] block, nothing that stores or serves
    assert package_imports("server")["server.analysis"] <= {"server.studies"}


def private_imports(top: str) -> list[str]:
    """``path:line name`` of every import of another module's private (``_``) name under ``top``."""
    found = []
    for path in sorted((ROOT / top).rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module != "__future__":
                found += [f"{path.relative_to(ROOT)}:{node.lineno} {a.name}" for a in node.names
                          if a.name.startswith("_")]
    return found


@pytest.mark.parametrize("top", ["server", "anim_core"])
def test_no_module_imports_another_ones_private_names(top):
    assert private_imports(top) == []
