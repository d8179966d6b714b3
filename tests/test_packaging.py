"""What an installed animstudy needs lies inside its packages (issue 23): nothing found through the checkout."""

import tomllib
from fnmatch import fnmatch
from pathlib import Path

import server
from server.studies.studyfile import THESIS_FILE, load_study_file

ROOT = Path(__file__).resolve().parents[1]


def test_the_default_study_file_is_package_data():
    package = Path(server.__file__).resolve().parent
    path = THESIS_FILE.parent.resolve() / THESIS_FILE.name  # a link in the checkout: its place, not its target
    assert path.is_relative_to(package), f"{THESIS_FILE} is outside the server package"
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["server"]
    relative = path.relative_to(package).as_posix()
    assert any(fnmatch(relative, g) for g in globs), f"{relative} matches none of {globs}"
    assert load_study_file(THESIS_FILE).slug == "thesis"


def test_the_checkout_and_the_package_hold_one_default_study():
    assert THESIS_FILE.resolve() == (ROOT / "studies" / "thesis.toml").resolve()
