"""The source data files: where they are in the data directory, what their content must be, and loading them.

anim_core opens no data directory: its loaders take file paths (:func:`anim_core.rig.character.load_character`,
:func:`anim_core.io.bvh.read_bvh`, :func:`anim_core.io.gltf.read_gltf`); this module finds and verifies those files
and turns the loaders' errors into :class:`AssetError` naming the file.  A glTF character (and its mapping file)
is a user's file named by the clip-set file: under the data directory or absolute, not checksum-listed.

The repository ships them in ``data/`` (see its README for origins and licenses); the server reads them from the
data directory of its settings (``ANIMSTUDY_DATA_DIR``, default that folder).  Each file may be stored
gzip-compressed (``name.gz``, as shipped) or plain; the checksum is that of the uncompressed content, which is what
the public origins publish.
"""

from __future__ import annotations

import gzip
import hashlib
from pathlib import Path

from anim_core.io.bvh import Bvh, BvhError, read_bvh
from anim_core.io.gltf import GltfError, read_gltf
from anim_core.rig.character import Character, CharacterError, load_character
from anim_core.rig.gltf_character import MappedCharacter, character_from_gltf
from anim_core.rig.rigmap import RigMapError, read_mapping_file

#: path in the data directory (as mirrored, gzip-compressed where marked) -> sha256 of the uncompressed content
CHECKSUMS: dict[str, str] = {
    "mocap/cmu/12_03_walk.bvh.gz": "23e0f37e31a07642d09ee1bdc6eb55ca8878f74365abff2f78423759fdaca0ee",
    "mocap/cmu/02_01_walk.bvh.gz": "c0bdbc2efaa3f5a6c7b74ee8a5baab06b86deda4d506083fb6a28a2d128f11eb",
    "mocap/cmu/09_11_run.bvh.gz": "fb948896c3791cc8b3f6004b272becde137a0dbf5ac4ab2c62a0dc8fb9417811",
    "mocap/cmu/115_06_crouch_first164.bvh.gz": "bdc38a38c8268c232a2a4fb470fa70d2b1ddd98bd96670a118c2da33bb8e7f5d",
    "mocap/cmu/113_21_idle_30fps.bvh.gz": "62b94d6b882fa8a7954c06ddc74f99b088d69ea977bc433c7b9525402d067384",
    "mocap/cmu/113_27_wave_30fps.bvh.gz": "ce783519ae5b8400abe813b2ba7be4cbe5386942409b4aed438f287708098cf4",
    "character/makehuman_cmu_mb/base.obj.gz": "8e761e6624b8f54536409135d1636da63b32486a90d4897f84e121d144f6fb4c",
    "character/makehuman_cmu_mb/rig.cmu_mb.json": "a751d730091304de2a7f7407a57976e86f71f75125e21fa2626ca5c661a6ad68",
    "character/makehuman_cmu_mb/weights.cmu_mb.json.gz":
        "e349f27b120b848858fca21c386b257de0b93e7ec26113f6dd2e8caa8ce11e9b",
}


CHARACTER_DIR = "character/makehuman_cmu_mb"
CHARACTER_FILES = tuple(f"{CHARACTER_DIR}/{name}" for name in
                        ("rig.cmu_mb.json", "weights.cmu_mb.json.gz", "base.obj.gz"))


class AssetError(ValueError):
    """A source file is missing, corrupt or not what the project expects."""


def check_data_dir(data_dir: Path) -> Path:
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise AssetError(f"data directory {data_dir} does not exist; set ANIMSTUDY_DATA_DIR to the folder holding "
                         f"mocap/ and character/, or unset it to use the sample data in the repository's data/ "
                         f"(see docs/reference/data.md)")
    return data_dir


def resolve(data_dir: Path, name: str) -> Path:
    """The file for ``name`` in ``data_dir``: as named, or its uncompressed/compressed twin."""
    base = check_data_dir(data_dir)
    candidates = [base / name, base / name.removesuffix(".gz") if name.endswith(".gz") else base / f"{name}.gz"]
    for path in candidates:
        if path.is_file():
            return path
    raise AssetError(f"missing file {base / name} (see docs/reference/data.md: the repository's data/ folder ships it)")


def read_bytes(path: Path) -> bytes:
    """Content of ``path``, decompressed if it ends in ``.gz``; corrupt archives raise :class:`AssetError`."""
    try:
        data = path.read_bytes()
        return gzip.decompress(data) if path.suffix == ".gz" else data
    except (OSError, EOFError) as exc:
        raise AssetError(f"cannot read {path}: {exc} (corrupt file?)") from None


def sha256_content(path: Path) -> str:
    """Checksum of a data file's uncompressed content (what :data:`CHECKSUMS` lists)."""
    return hashlib.sha256(read_bytes(path)).hexdigest()


def verify(data_dir: Path, name: str) -> Path:
    """Resolve ``name`` and check its content against :data:`CHECKSUMS` (names not listed are not checked)."""
    path = resolve(data_dir, name)
    expected = CHECKSUMS.get(name) or CHECKSUMS.get(f"{name}.gz")
    if expected is not None:
        actual = sha256_content(path)
        if actual != expected:
            raise AssetError(f"{path} is corrupt or a different version: sha256 of its content is {actual}, "
                             f"expected {expected}")
    return path


#: The character loaded from files of these content checksums (its arrays are read-only): parsing the mesh and the
#: weights takes 0.3 s, and a server or a command builds clip sets and renders with it many times.
_CHARACTERS: dict[tuple[str, ...], Character] = {}


def character(data_dir: Path) -> Character:
    """The character of the data directory, its files verified against :data:`CHARACTER_FILES`' checksums (loaded
    once per process: verified files have one content)."""
    paths = tuple(verify(data_dir, name) for name in CHARACTER_FILES)
    key = tuple(CHECKSUMS[name] for name in CHARACTER_FILES)  # what verify() just checked each file against
    if key not in _CHARACTERS:
        try:
            _CHARACTERS[key] = load_character(*paths)
        except CharacterError as exc:
            raise AssetError(str(exc)) from None
    return _CHARACTERS[key]


def sha256(path: Path) -> str:
    """Checksum of a file's content as stored (a glTF or mapping file is hashed as is)."""
    try:
        return hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise AssetError(f"cannot read {path}: {exc}") from None


def user_file(data_dir: Path, name: str, what: str) -> Path:
    """A file the clip-set file names: ``name`` under the data directory, or an absolute path."""
    path = check_data_dir(data_dir) / name  # an absolute name stays itself
    if not path.is_file():
        raise AssetError(f"{what} file {path} does not exist (a path under the data directory {data_dir} or an "
                         f"absolute path)")
    return path


def gltf_character(data_dir: Path, gltf: str, mapping: str | None = None, units: str | None = None,
                   up_axis: str | None = None) -> MappedCharacter:
    """A skinned glTF character (docs/motion/your-own-motion.md, *A glTF character*); every error names the file."""
    path = user_file(data_dir, gltf, "glTF character")
    explicit = None
    if mapping is not None:
        mapping_path = user_file(data_dir, mapping, "joint mapping")
        try:
            explicit = read_mapping_file(mapping_path)
        except RigMapError as exc:
            raise AssetError(str(exc)) from None
    try:
        # The character is its skin and bind pose: animations in the file (a character exported with its
        # takes) are not read, so none of them can refuse it.
        return character_from_gltf(read_gltf(path, animations=False), explicit, units, up_axis)
    except (GltfError, CharacterError) as exc:
        # The message starts with the file's name; give its folder too.
        raise AssetError(f"glTF character {path.parent}/{exc}") from None


def motion(data_dir: Path, name: str) -> Bvh:
    """The BVH file ``name`` of the data directory (checksum-verified where listed)."""
    path = verify(data_dir, name)
    try:
        return read_bvh(path)
    except BvhError as exc:
        raise AssetError(f"corrupt motion file: {exc}") from None
