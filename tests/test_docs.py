"""The README is the short entry page and the manual's generated reference pages come from the code (the site
itself is built by `mkdocs build --strict` in `make test`)."""

from __future__ import annotations

import argparse
import importlib.util
import re
from pathlib import Path

from server.cli import build_parser
from server.studies import studyfile
from server.studies.columns import COLUMNS, EXPORT_COLUMNS, QUESTIONS_BEFORE, data_dictionary_markdown
from server.studies.service import EXPORT_COLUMNS as SERVICE_EXPORT_COLUMNS

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def _hooks():
    spec = importlib.util.spec_from_file_location("mkdocs_hooks", ROOT / "tools" / "mkdocs_hooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_is_a_short_entry_page_with_the_two_commands():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines; move the detail into a page under docs/"
    text = "\n".join(lines)
    assert "make run" in text and "make test" in text


def test_readme_links_point_at_existing_files():
    targets = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", README.read_text(encoding="utf-8"))
    local = [t for t in targets if not re.match(r"^[a-z]+://", t)]
    assert local, "the README links into docs/"
    assert [t for t in local if not (ROOT / t).is_file()] == []


def test_one_export_column_list():
    assert SERVICE_EXPORT_COLUMNS is EXPORT_COLUMNS
    assert studyfile.RESERVED_IDS == frozenset(EXPORT_COLUMNS)
    assert len(set(EXPORT_COLUMNS)) == len(EXPORT_COLUMNS) and QUESTIONS_BEFORE in EXPORT_COLUMNS
    assert all(c.type and c.meaning for c in COLUMNS)
    assert not (ROOT / "server" / "studies" / "DATA_DICTIONARY.md").exists()


def test_data_dictionary_lists_every_column_once_in_export_order():
    text = data_dictionary_markdown()
    rows = re.findall(r"^\| `([a-z_]+)` \|", text.split("## Columns of exports before")[0], flags=re.M)
    assert rows == list(EXPORT_COLUMNS)
    # The question columns are documented where the export puts them.
    assert text.index("| *question id* |") < text.index(f"| `{QUESTIONS_BEFORE}` |")


def _commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out += [(*path, name), *_commands(sub, (*path, name))]
    return out


def test_cli_reference_has_every_subcommand_and_option():
    parser = build_parser()
    text = _hooks().cli_markdown(parser)
    commands = _commands(parser)
    assert ("study", "export") in commands and ("loadtest",) in commands
    for command in commands:
        assert f"`animstudy {' '.join(command)}`" in text
    for option in ("--every-clip", "--variants", "--owner", "--crash-at", "--mapping"):
        assert f"`{option}`" in text


def test_cli_reference_picks_up_a_new_subcommand():
    parser = build_parser()
    study = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices["study"]
    study_sub = next(a for a in study._actions if isinstance(a, argparse._SubParsersAction))
    added = study_sub.add_parser("archive", help="archive a closed study")
    added.add_argument("--keep-videos", action="store_true", help="leave its videos in the media folder")
    text = _hooks().cli_markdown(parser)
    assert "### `animstudy study archive`" in text and "`--keep-videos`" in text
