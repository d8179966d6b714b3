"""Bounded fuzzing of the readers of untrusted files (issue 26): BVH, glTF, study file (as text and as bytes),
clip-set file, and study archives (issue 36: the ZIP's bytes, and changes deep in its index).

Each property feeds mutations of a valid file to its reader and allows two outcomes only: a result, or the reader's
own error (BvhError, GltfError, StudyFileError, ConfigError; for an archive ArchiveError, or Conflict when the
study was imported before, with no file left behind); any other exception is a bug.  The memory a reader
takes for one input is measured (``tracemalloc``, which numpy reports to) and must stay within the uploads' bound,
50 × the input's size + 200 MB, and the readers get the frame·joint bound the upload service gives them.

Hypothesis (60 examples per reader, no example database) keeps the whole file at about half a minute on an idle
machine;
``FUZZ_EXAMPLES=5000 pytest tests/test_fuzz_readers.py`` runs a longer campaign.
"""

from __future__ import annotations

import json
import os
import tracemalloc
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from anim_core.clips.build import ConfigError
from anim_core.io.bvh import BvhError, format_bvh, parse_bvh, read_bvh
from anim_core.io.gltf import GltfError, read_gltf
from server.clipset.config import load_config
from server.studies.studyfile import THESIS_FILE, StudyFileError, parse_study_text
from server.uploads.service import max_frame_joints

EXAMPLES = int(os.environ.get("FUZZ_EXAMPLES", "60"))
FUZZ = settings(max_examples=EXAMPLES, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
ROOT = Path(__file__).resolve().parents[1]


def bounded(size: int, call):
    """``call()``'s result with the peak memory it allocated checked against 50 × ``size`` + 200 MB."""
    tracemalloc.start()
    try:
        result = call()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= 50 * size + 200e6, f"{peak / 2**20:.0f} MiB for {size} bytes"
    return result


def mutate(data: bytes, edits: list[tuple[int, int, bytes]]) -> bytes:
    """``data`` with each (position, deleted length, inserted bytes) applied (positions wrap around)."""
    out = bytearray(data)
    for at, cut, insert in edits:
        at %= max(len(out), 1)
        out[at:at + cut] = insert
    return bytes(out)


EDITS = st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 8),
                           st.one_of(st.binary(max_size=6),
                                     st.sampled_from([b"0", b"-1", b"1e308", b"nan", b"999999999", b"{", b"}", b"\n",
                                                      b"JOINT x\n{\nOFFSET 0 0 0\nCHANNELS 0\n}\n", b"CHANNELS 6 ",
                                                      b"Frames: 1000000", b"End Site", b"\xff\xfe", b"\r\n"]))),
                 min_size=1, max_size=6)


@pytest.fixture(scope="module")
def small_bvh(data) -> bytes:
    bvh = read_bvh(data / "mocap" / "cmu" / "113_21_idle_30fps.bvh.gz")
    from anim_core.io.bvh import Bvh

    return format_bvh(Bvh(bvh.skeleton, bvh.channels, bvh.end_sites, bvh.frame_time, bvh.motion[:4])).encode()


@FUZZ
@given(edits=EDITS)
def test_fuzz_bvh(small_bvh, edits):
    raw = mutate(small_bvh, edits)
    text = raw.decode("latin-1")
    try:
        bounded(len(raw), lambda: parse_bvh(text, "fuzz.bvh", max_frame_joints(len(raw))))
    except BvhError:
        pass


@pytest.fixture(scope="module")
def small_gltf(tmp_path_factory) -> dict:
    from tests.hostile_files import _chain_gltf

    path = tmp_path_factory.mktemp("fuzz") / "chain.gltf"
    _chain_gltf(path, 4, [0.0, 1 / 30, 2 / 30])
    return json.loads(path.read_text())


# Fields of the glTF document worth breaking, and values to break them with.
GLTF_FIELDS = [("accessors", "count"), ("accessors", "byteOffset"), ("accessors", "componentType"),
               ("accessors", "type"), ("accessors", "bufferView"), ("accessors", "normalized"),
               ("bufferViews", "byteStride"), ("bufferViews", "byteOffset"), ("bufferViews", "byteLength"),
               ("bufferViews", "buffer"), ("nodes", "children"), ("nodes", "rotation"), ("nodes", "scale"),
               ("nodes", "matrix"), ("skins", "joints"), ("skins", "inverseBindMatrices"), ("meshes", "primitives"),
               ("animations", "samplers"), ("animations", "channels"), ("buffers", "byteLength")]
VALUES = st.one_of(st.integers(-3, 3), st.integers(0, 2**32), st.sampled_from([5120, 5121, 5123, 5125, 5126, "VEC4",
                                                                               "MAT4", "SCALAR", None, [], {}, [0],
                                                                               [0, 0, 0, 1], 1e308, "x"]),
                   st.lists(st.integers(-1, 6), max_size=5))


@FUZZ
@given(changes=st.lists(st.tuples(st.sampled_from(GLTF_FIELDS), st.integers(0, 40), VALUES), min_size=1,
                        max_size=4))
def test_fuzz_gltf(small_gltf, tmp_path_factory, changes):
    doc = json.loads(json.dumps(small_gltf))
    for (array, key), index, value in changes:
        items = doc.get(array) or []
        if items:
            items[index % len(items)][key] = value
    path = tmp_path_factory.getbasetemp() / "fuzz.gltf"
    path.write_text(json.dumps(doc))
    size = path.stat().st_size
    try:
        bounded(size, lambda: read_gltf(path, max_frame_joints=max_frame_joints(size)))
    except GltfError:
        pass


@pytest.fixture(scope="module")
def thesis_text() -> str:
    return THESIS_FILE.read_text(encoding="utf-8")


TOML_BITS = st.sampled_from(["[", "]", "{", "}", "=", "\"", "'''", "\n", "[[questions]]\n", "[design]\n",
                             "repeats = 99999999999999999999\n", "a = " + "[" * 3000, "\u202e", "{code:>9}",
                             "url = \"https://{PROLIFIC_PID}/\"\n", "x.y.z = 1\n", "1979-05-27T07:32:00Z", "inf",
                             "nan", "\\u0000", "\x00"])


@FUZZ
@given(edits=st.lists(st.tuples(st.integers(0, 10**5), st.integers(0, 12), st.one_of(TOML_BITS, st.text(max_size=8))),
                      min_size=1, max_size=5))
def test_fuzz_study_file(thesis_text, edits):
    text = thesis_text
    for at, cut, insert in edits:
        at %= len(text) or 1
        text = text[:at] + insert + text[at + cut:]
    try:
        bounded(len(text.encode("utf-8", "surrogatepass")), lambda: parse_study_text(text, "fuzz.toml"))
    except StudyFileError:
        pass


@FUZZ
@given(edits=st.lists(st.tuples(st.integers(0, 10**5), st.integers(0, 12), st.one_of(TOML_BITS, st.text(max_size=8))),
                      min_size=1, max_size=5))
def test_fuzz_clip_set_file(tmp_path_factory, edits):
    text = (ROOT / "server" / "clipset" / "thesis.toml").read_text(encoding="utf-8")
    for at, cut, insert in edits:
        at %= len(text) or 1
        text = text[:at] + insert + text[at + cut:]
    path = tmp_path_factory.getbasetemp() / "clips.toml"
    try:
        path.write_text(text, encoding="utf-8")
    except UnicodeEncodeError:  # a lone surrogate cannot be a file's text
        return
    try:
        bounded(path.stat().st_size, lambda: load_config(path))
    except ConfigError:
        pass


# --- study archives and study files as bytes (issue 36) ---------------------------------------------------------

@pytest.fixture(scope="module")
def archive_setup(tmp_path_factory):
    """An exported study archive (fake videos) and an empty second server to import it into."""
    from sqlalchemy.orm import Session

    from server.db import make_engine, migrate
    from server.studies import service
    from server.studies.archive import export_archive
    from tests.server_fixtures import study_file, write_fake_media

    root = tmp_path_factory.mktemp("archive-fuzz")
    first = make_engine(f"sqlite:///{root / 'one.db'}")
    migrate(first)
    media = root / "media1"
    write_fake_media(media)
    with Session(first, expire_on_commit=False) as db:
        study = service.create_study(db, service.RenderManifest.model_validate_json(
            (media / "manifest.json").read_text()), study_file(slug="fuzzed"), media_dir=media)
        path = export_archive(study, media, root / "fuzzed.zip")
    first.dispose()
    second = make_engine(f"sqlite:///{root / 'two.db'}")
    migrate(second)
    yield path, second, root
    second.dispose()


def import_bounded(setup, raw: bytes) -> None:
    """Import the archive ``raw`` into the second server: a study, or ArchiveError or Conflict (a ServiceError of
    the import's own), within the memory bound; a refused import leaves no file in the media directory."""
    from sqlalchemy import delete
    from sqlalchemy.orm import Session

    from server.errors import Conflict
    from server.studies.archive import ArchiveError, import_archive
    from server.studies.models import Study

    _, engine, root = setup
    media = root / "media2"
    path = root / "input.zip"
    path.write_bytes(raw)
    before = set(media.iterdir()) if media.exists() else set()
    with Session(engine) as db:
        try:
            bounded(len(raw), lambda: import_archive(db, path, media))
        except (ArchiveError, Conflict):
            assert (set(media.iterdir()) if media.exists() else set()) == before
        else:  # imported: taken away again, so the next example can import too
            db.execute(delete(Study))
            db.commit()


@FUZZ
@given(edits=EDITS)
def test_fuzz_import_archive_bytes(archive_setup, edits):
    import_bounded(archive_setup, mutate(archive_setup[0].read_bytes(), edits))


# Values to put into an archive's index: wrong types, huge numbers, deep nesting, names with a newline.
INDEX_VALUES = st.one_of(VALUES, st.text(max_size=12), st.sampled_from([
    10**400, -1, "0" * 24 + ".mp4\n", "../x", {"digest": 1}, [[[[[]]]]], {"clips": [], "pairs": []}, True]))


@FUZZ
@given(changes=st.lists(st.tuples(st.lists(st.integers(0, 30), min_size=1, max_size=6), INDEX_VALUES),
                        min_size=1, max_size=4),
       redigest=st.booleans(), compression=st.sampled_from([0, 8, 12, 14]))
def test_fuzz_import_archive_index(archive_setup, changes, redigest, compression):
    """Changes deep inside ``archive.json`` (with the set's digest made right again, or not), in any of the
    compression methods zipfile writes."""
    import io
    import zipfile

    from server.stimuli.service import content_digest

    with zipfile.ZipFile(archive_setup[0]) as z:
        members = {name: z.read(name) for name in z.namelist()}
    index = json.loads(members["archive.json"])
    for steps, value in changes:  # walk down by index into the keys or items, then replace what is there
        node = index
        for step in steps[:-1]:
            children = list(node.values()) if isinstance(node, dict) else node if isinstance(node, list) else []
            if not children or not isinstance(children[step % len(children)], dict | list):
                break
            node = children[step % len(children)]
        value = json.loads(json.dumps(value))  # a copy: the same sampled list put into itself is circular
        if isinstance(node, dict) and node:
            node[list(node)[steps[-1] % len(node)]] = value
        elif isinstance(node, list) and node:
            node[steps[-1] % len(node)] = value
    stimulus_set = index.get("stimulus_set")
    if redigest and isinstance(stimulus_set, dict) and isinstance(stimulus_set.get("content"), dict):
        stimulus_set["digest"] = content_digest(stimulus_set["content"])
    members["archive.json"] = json.dumps(index).encode()
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=compression) as w:
        for name, data in members.items():
            w.writestr(name, data)
    import_bounded(archive_setup, out.getvalue())


@FUZZ
@given(edits=EDITS)
def test_fuzz_study_file_bytes(thesis_text, tmp_path_factory, edits):
    """The study file reader on bytes: invalid UTF-8, NULs, a byte-order mark, cut anywhere."""
    from server.studies.studyfile import load_study_file

    raw = mutate(thesis_text.encode("utf-8"), edits)
    path = tmp_path_factory.getbasetemp() / "study.toml"
    path.write_bytes(raw)
    try:
        bounded(len(raw), lambda: load_study_file(path))
    except StudyFileError:
        pass
