"""MkDocs hooks (``hooks:`` in mkdocs.yml): the reference pages that are generated from the code at every build, so
they cannot go stale.

- ``reference/cli.md``: every ``animstudy`` subcommand and option, walked from ``server.cli.build_parser()`` (a
  subcommand added there appears without touching the docs).
- ``reference/data-dictionary.md``: the export columns, from ``server.studies.columns`` (the same Markdown
  ``GET /api/v1/data-dictionary`` serves).

Both are pages of the site only (``File.generated``): nothing is written into docs/.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

CLI_PAGE = "reference/cli.md"
DATA_DICTIONARY_PAGE = "reference/data-dictionary.md"
# MathJax (npm package mathjax@3, installed by `make docs` into var/node-docs: in var/node npm would prune axe-core)
# is copied into the site when present, so formulas render without fetching anything; without it they show as TeX.
MATHJAX = Path(__file__).resolve().parents[1] / "var/node-docs/node_modules/mathjax/es5/tex-svg.js"
USAGE_WIDTH = 80  # fits the theme's code block without scrolling


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of each subcommand of ``parser``, in definition order."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            out += [(name, helps.get(name, ""), sub) for name, sub in action.choices.items()]
    return out


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _options_table(parser: argparse.ArgumentParser) -> list[str]:
    rows = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction | argparse._HelpAction):
            continue
        if action.option_strings:
            name = ", ".join(f"`{o}`" for o in action.option_strings)
            if action.nargs != 0 and action.choices is None:
                name += f" `{action.metavar or action.dest.upper()}`"
        else:
            name = f"`{action.metavar or action.dest}`"
        if action.choices is not None:
            name += " (" + ", ".join(f"`{c}`" for c in action.choices) + ")"
        default = action.default
        shown = "" if default is None or default is False or action.required or not action.option_strings \
            else f"`{default}`"
        required = "yes" if action.required or not action.option_strings else ""
        rows.append(f"| {_cell(name)} | {required} | {_cell(shown)} | {_cell(action.help or '')} |")
    if not rows:
        return []
    return ["| argument | required | default | what |", "|---|---|---|---|", *rows, ""]


def _walk(parser: argparse.ArgumentParser, path: list[str], help_text: str, lines: list[str]) -> None:
    subcommands = _subcommands(parser)
    if path:
        lines += [f"{'#' * min(len(path), 6)} `{' '.join(path)}`", ""]
        if help_text:
            lines += [help_text[:1].upper() + help_text[1:] + ".", ""]
    parser.formatter_class = lambda prog: argparse.HelpFormatter(prog, width=USAGE_WIDTH)
    lines += ["```text", parser.format_usage().strip(), "```", ""]
    lines += _options_table(parser)
    for name, sub_help, sub in subcommands:
        _walk(sub, [*path, name] if path else ["animstudy", name], sub_help, lines)


def cli_markdown(parser: argparse.ArgumentParser) -> str:
    """The reference of a command line as Markdown: per (sub)command its usage and a table of its arguments."""
    lines = ["# Command line reference", "",
             f"Generated from the argparse definitions in `server/cli.py` (`{parser.prog} --help` prints the same); "
             "a subcommand is a section, nested subcommands are subsections.", ""]
    _walk(parser, [], "", lines)
    return "\n".join(lines)


def on_files(files: Files, config: Any) -> Files:
    from server.cli import build_parser
    from server.studies.columns import data_dictionary_markdown

    for path, content in ((CLI_PAGE, cli_markdown(build_parser())), (DATA_DICTIONARY_PAGE, data_dictionary_markdown())):
        if files.get_file_from_path(path) is not None:
            raise ValueError(f"docs/{path} is generated at build time (tools/mkdocs_hooks.py); remove the file")
        files.append(File.generated(config, path, content=content))
    return files


def on_post_build(config: Any) -> None:
    if MATHJAX.is_file():
        target = Path(config["site_dir"]) / "javascripts" / MATHJAX.name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(MATHJAX, target)
