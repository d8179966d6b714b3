"""The commands README.md and docs/getting-started.md tell a newcomer to type, executed (issue 37): a renamed
subcommand or option, or a command that fails, fails here instead of on a reader's machine.

Every shell line of their ```sh blocks and every inline `animstudy ...` / `.venv/bin/animstudy ...` command is
checked: its subcommands must exist and each of its --options must be in that subcommand's --help.  The cheap ones
also run for real on a temporary ANIMSTUDY_VAR_DIR (`study validate` on the example study, `study schema`).  Not run
for real, and why: `make run` serves until stopped and `make test` is this suite (both dry-run with `make -n`, which
fails for a missing target); `study create`, `clips build`, `render` and `serve` build or render everything or serve
(their own tests, e.g. tests/test_cli.py, run them on small inputs).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = (ROOT / "README.md", ROOT / "docs" / "getting-started.md")
ANIMSTUDY = Path(sys.executable).parent / "animstudy"
# Run for real: cheap, read-only apart from the temporary var dir.
RUN = {("study", "validate"), ("study", "schema")}


def shell_lines(text: str) -> list[str]:
    """The command lines of the ```sh blocks, comments dropped."""
    lines = []
    for block in re.findall(r"^```(?:sh|bash|shell|console)\n(.*?)^```", text, flags=re.M | re.S):
        lines += [line.split("#")[0].strip() for line in block.splitlines() if line.split("#")[0].strip()]
    return lines


def inline_commands(text: str) -> list[str]:
    """Inline code that is an animstudy command line."""
    return [c for c in re.findall(r"`([^`\n]+)`", text) if re.match(r"(\.venv/bin/)?animstudy( |$)", c)]


def expand(command: str) -> list[list[str]]:
    """``clips inspect|convert|export`` stands for three commands; ``[--host]`` for the option ``--host``."""
    tokens = command.replace("[", " ").replace("]", " ").split()[1:]
    out: list[list[str]] = [[]]
    for token in tokens:
        if "|" in token and not token.startswith("-"):
            out = [[*o, alt] for o in out for alt in token.split("|")]
        else:
            out = [[*o, token] for o in out]
    return out


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, str]:
    var = tmp_path_factory.mktemp("var")
    return {**os.environ, "ANIMSTUDY_VAR_DIR": str(var)}


def run(args: list[str], env: dict[str, str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(ANIMSTUDY), *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=300)


@cache
def _help(words: tuple[str, ...], var_dir: str) -> str:
    done = run([*words, "--help"], {**os.environ, "ANIMSTUDY_VAR_DIR": var_dir}, ROOT)
    assert done.returncode == 0, f"animstudy {' '.join(words)} --help failed:\n{done.stderr}"
    return done.stdout


def subcommand(tokens: list[str], var_dir: str) -> tuple[tuple[str, ...], str]:
    """The subcommand ``tokens`` name, and its --help; a word where a subcommand must stand fails."""
    words: tuple[str, ...] = ()
    for token in (t for t in tokens if not t.startswith("-")):
        text = _help(words, var_dir)
        choices = re.search(r"\{([\w,-]+)\}\s+\.\.\.", text.split("\n\n")[0])  # subparsers: "{a,b} ..."
        if choices and token in choices.group(1).split(","):
            words = (*words, token)
            continue
        # A command group takes only its subcommands; a leaf command's first positional argument ends the name.
        assert choices is None, f"animstudy {' '.join(words)} has no subcommand {token!r}"
        break
    return words, _help(words, var_dir)


def doc_commands() -> list[tuple[str, str]]:
    out = []
    for page in PAGES:
        text = page.read_text(encoding="utf-8")
        out += [(page.name, c) for c in shell_lines(text) + inline_commands(text)]
    return out


def test_the_pages_have_commands_to_check():
    # Guards the extraction: if the regexes stopped matching, every other test here would pass vacuously.
    commands = [c for _, c in doc_commands()]
    assert "make run" in commands and "make test" in commands
    assert any("study validate" in c for c in commands)


@pytest.mark.parametrize(("page", "command"), doc_commands(), ids=lambda v: v)
def test_documented_command_exists_and_cheap_ones_run(page, command, env, tmp_path):
    if command.startswith("make "):
        target = command.split()[1]
        # -n prints the recipe without running it; a missing target is an error.
        done = subprocess.run(["make", "-n", target], cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        return
    assert command.startswith(("animstudy", ".venv/bin/animstudy")), f"{page}: unknown command {command!r}"
    for tokens in expand(command):
        words, text = subcommand(tokens, env["ANIMSTUDY_VAR_DIR"])
        for option in (t.split("=")[0] for t in tokens if t.startswith("--")):
            assert option in text, f"{page}: `animstudy {' '.join(words)}` has no option {option}"
        if words in RUN:
            # The newcomer's study file is the example (README step 1 copies it).
            shutil.copy(ROOT / "studies" / "example.toml", tmp_path / "mystudy.toml")
            done = run(tokens, env, tmp_path)
            assert done.returncode == 0, f"{page}: `{command}` failed:\n{done.stdout}{done.stderr}"
