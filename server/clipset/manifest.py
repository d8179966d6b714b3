"""The clip manifest (``manifest.json`` of ``animstudy clips build``) and its ``.npz`` files: the one schema,
written and read here only.

Version 2 (this one) names each clip's animation, condition, method and method parameters; readers never parse
clip ids.  A manifest of another version, or one that does not validate, raises :class:`ManifestError` saying to
rebuild the clip set.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError

from anim_core.clips.record import BuiltClip
from anim_core.methods.conditions import Kind

MANIFEST = "manifest.json"
VERSION = 2
#: The arrays of each clip's ``.npz`` (docs/reference/manifests.md).
CLIP_ARRAYS = ("joint_names", "parents", "offsets", "bind_rotations", "bind_positions", "times", "local_rotations",
               "root_positions", "world_rotations", "world_positions", "key_times", "key_rotations")
M = TypeVar("M", bound=BaseModel)


class ManifestError(ValueError):
    """A manifest is missing, corrupt or of another version; the message says what to rebuild."""


class _Model(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Units(_Model):
    length: Literal["m"] = "m"
    time: Literal["s"] = "s"
    up: Literal["+y"] = "+y"
    quaternion: Literal["w,x,y,z"] = "w,x,y,z"


class RenderOptions(_Model):
    """Per-clip render settings of a render-time condition: ``skin_influences``, the strongest skin weights kept
    per vertex (renormalised) when the renderer skins the clip (method ``skin_influences``)."""

    skin_influences: int | None = Field(None, ge=1, le=8)


class ClipEntry(_Model):
    """One clip of a clip set, the one record of it on the server: the builder writes it, the renderer, the
    pipeline and the stimulus sets read it.  ``file`` (``<id>.npz``, or ``<id>.<hash>.npz`` when it replaced one,
    beside the manifest) holds its arrays (docs/reference/manifests.md); :attr:`path` and :attr:`digest` are known
    once it was read from a directory."""

    id: str
    animation: str
    kind: Kind
    condition: str
    method: str
    params: dict[str, Any]
    key_count: int = Field(ge=1)
    duration_s: float = Field(gt=0)
    fps: int = Field(ge=1)
    frames: int = Field(ge=1)
    playback: Literal["loop", "pingpong"]
    in_place: bool
    root_speed_mps: float = Field(ge=0)
    metrics: dict[str, float | int | None]
    source: dict[str, Any]
    file: str
    #: the ladder (``[[ladders]]`` of the clip-set file) the condition is a level of, and the level
    ladder: str | None = None
    level: float | int | None = None
    #: how the renderer draws the clip otherwise than by default (render-time conditions); None: the default
    render: RenderOptions | None = None
    _dir: Path | None = PrivateAttr(default=None)
    _digest: str | None = PrivateAttr(default=None)

    @property
    def path(self) -> Path:
        """The clip's ``.npz`` file (the entry must come from :func:`read_clip_manifest`)."""
        if self._dir is None:
            raise ValueError(f"the clip {self.id!r} was not read from a clip set directory")
        return self._dir / self.file

    @property
    def digest(self) -> str:
        """sha256 of the clip's arrays (names, dtypes, shapes, bytes) and of its :attr:`render` settings if it has
        any, read once: clips with equal arrays and settings share their videos.  Taken from the file rather than
        the manifest, so that arrays changed on disk are rendered anew."""
        if self._digest is None:
            digest = arrays_digest(self.path)
            if self.render is not None:  # the same motion skinned otherwise is another video
                text = json.dumps({"arrays": digest, "render": self.render.model_dump()}, sort_keys=True)
                digest = hashlib.sha256(text.encode()).hexdigest()
            self._digest = digest
        return self._digest


class CharacterEntry(_Model):
    """The character the clips were built for: ``gltf`` None is the MakeHuman character, else the glTF file (as the
    clip-set file names it) with its ``mapping`` file and ``units``/``up_axis`` overrides; ``files``: sha256 of
    each file it was made from (the renderer refuses files that changed since)."""

    gltf: str | None = None
    mapping: str | None = None
    units: str | None = None
    up_axis: str | None = None
    files: dict[str, str]


class ClipManifest(_Model):
    version: Literal[2] = VERSION
    units: Units = Units()
    #: None in manifests written before it was recorded: those were all built for the MakeHuman character.
    character: CharacterEntry | None = None
    clips: list[ClipEntry]

    def clip(self, animation: str, condition: str) -> ClipEntry | None:
        return next((c for c in self.clips if c.animation == animation and c.condition == condition), None)


def entry(c: BuiltClip, file: str | None = None) -> ClipEntry:
    return ClipEntry(id=c.id, animation=c.animation, kind=c.kind, condition=c.condition, method=c.method,
                     params=c.params, key_count=int(c.key_times.size), duration_s=c.duration_s, fps=c.fps,
                     frames=c.n_frames, playback=c.playback, in_place=c.in_place, root_speed_mps=c.root_speed_mps,
                     metrics=c.metrics, source={k: v for k, v in c.source.items() if k != "character"},
                     file=file or f"{c.id}.npz", ladder=c.ladder, level=c.level,
                     render=None if c.render is None else RenderOptions.model_validate(c.render))


def _readable(clips_dir: Path) -> ClipManifest | None:
    """The manifest in ``clips_dir`` if there is a readable one (its files are then kept until it is replaced)."""
    try:
        return read_clip_manifest(clips_dir) if (clips_dir / MANIFEST).exists() else None
    except ManifestError:
        return None


def _write_clips(clips_dir: Path, clips: list[BuiltClip], current: ClipManifest | None) -> dict[str, str]:
    """Write each clip's ``.npz`` under a name the current manifest does not use (``<id>.npz``, or
    ``<id>.<hash>.npz`` while the current manifest names that one), through a temporary file; returns clip id ->
    file name.  No file the current manifest names is touched: a build killed before the manifest is replaced
    leaves the clip set as it was."""
    used = {e.file for e in current.clips} if current is not None else set()
    files = {}
    for c in clips:
        tmp = clips_dir / f".{c.id}.tmp.npz"
        np.savez_compressed(tmp, **c.arrays())
        name = f"{c.id}.npz"
        if name in used:
            name = f"{c.id}.{hashlib.sha256(tmp.read_bytes()).hexdigest()[:12]}.npz"
        tmp.replace(clips_dir / name)
        files[c.id] = name
    return files


def _drop_replaced(clips_dir: Path, before: ClipManifest | None, after: ClipManifest) -> None:
    """Remove the files of the previous manifest that the new one does not name (after the switch to it)."""
    if before is None:
        return
    keep = {e.file for e in after.clips}
    for e in before.clips:
        if e.file not in keep and Path(e.file).name == e.file:
            (clips_dir / e.file).unlink(missing_ok=True)


def unreferenced_clip_files(clips_dir: Path) -> list[Path]:
    """The clip files (``.npz``) of ``clips_dir`` that its manifest does not name: left by a build killed before it
    replaced the manifest.  Files newer than the manifest are kept (a running build writes its manifest last), and
    so is everything in a folder whose manifest is missing or unreadable (nothing says what is in use there)."""
    manifest = _readable(clips_dir)
    if manifest is None:
        return []
    named = {e.file for e in manifest.clips}
    written = (clips_dir / MANIFEST).stat().st_mtime
    return sorted(f for f in clips_dir.glob("*.npz")
                  if f.name not in named and f.is_file() and f.stat().st_mtime <= written)


def write_clip_set(clips: list[BuiltClip], out: Path) -> Path:
    """Write one ``.npz`` per clip and ``manifest.json`` (replacing a clip set there: its files stay until the new
    manifest has replaced its manifest, see :func:`_write_clips`); returns the manifest path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    records = [c.source.get("character") for c in clips]
    if any(r != records[0] for r in records):
        raise ValueError("the clips of one clip set were built for different characters")
    character = CharacterEntry.model_validate(records[0]) if records and records[0] else None
    before = _readable(out)
    files = _write_clips(out, clips, before)
    manifest = ClipManifest(character=character, clips=[entry(c, files[c.id]) for c in clips])
    path = write_json(out / MANIFEST, manifest)
    _drop_replaced(out, before, manifest)
    return path


def merge_clip_set(clips_dir: Path, built: list[BuiltClip]) -> Path:
    """Add built clips to the clip set in ``clips_dir`` (created if there is none), replacing the clips of the
    same animations; each ``.npz`` is written under a name the current manifest does not use
    (:func:`_write_clips`) and the manifest replaced last, so readers, and a build killed halfway, see the old clip
    set or the new one.  ManifestError if the clip set there is unreadable (merging into it would
    drop its clips) or was built for another character."""
    clips_dir = Path(clips_dir)
    clips_dir.mkdir(parents=True, exist_ok=True)
    current = read_clip_manifest(clips_dir) if (clips_dir / MANIFEST).exists() else None
    old = list(current.clips) if current is not None else []
    records = [c.source.get("character") for c in built]
    built_for = CharacterEntry.model_validate(records[0]) if records and records[0] else None
    # A manifest from before the character was recorded (None) was built for the MakeHuman body, as base_clip_set
    # builds the new clips then; any other difference mixes bodies.
    recorded = current.character if current is not None else None
    if any(r != records[0] for r in records) or (recorded is not None and built and recorded != built_for):
        raise ManifestError("the new clips were built for another character than the clip set's; rebuild the "
                            "clip set (`animstudy clips build`)")
    character = built_for if built else recorded
    files = _write_clips(clips_dir, built, current)
    replaced = {c.animation for c in built}
    entries = [e for e in old if e.animation not in replaced] + [entry(c, files[c.id]) for c in built]
    manifest = ClipManifest(character=character, clips=entries)
    path = write_json(clips_dir / MANIFEST, manifest)
    _drop_replaced(clips_dir, current, manifest)
    return path


def write_json(path: Path, model: BaseModel) -> Path:
    """Write ``model`` as JSON through a temporary file: readers never see a half-written manifest."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(model.model_dump_json(indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path


def read_json(path: Path, model: type[M], what: str, rebuild: str) -> M:
    """Read and validate a manifest; every problem is a :class:`ManifestError` that says to run ``rebuild``."""
    try:
        raw = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ManifestError(f"no {what} at {path} (run `{rebuild}`)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ManifestError(f"the {what} {path} is unreadable ({exc}); rebuild it with `{rebuild}`") from None
    version = model.model_fields["version"].default
    if not isinstance(raw, dict) or raw.get("version") != version:
        found = raw.get("version") if isinstance(raw, dict) else None
        raise ManifestError(f"the {what} {path} is of version {found!r}, this animstudy reads version {version}; "
                            f"rebuild it with `{rebuild}`")
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        first = exc.errors()[0]
        field = ".".join(str(p) for p in first["loc"])
        raise ManifestError(f"the {what} {path} is corrupt ({field}: {first['msg']}); rebuild it with "
                            f"`{rebuild}`") from None


def read_clip_manifest(clips_dir: Path) -> ClipManifest:
    """The manifest of the clip set in ``clips_dir``; its entries know their files (:attr:`ClipEntry.path`)."""
    manifest = read_json(Path(clips_dir) / MANIFEST, ClipManifest, "clip manifest", "animstudy clips build")
    for c in manifest.clips:
        c._dir = Path(clips_dir)
    return manifest


def arrays_digest(path: Path) -> str:
    """sha256 of the arrays of an ``.npz`` file: names, dtypes, shapes and bytes."""
    h = hashlib.sha256()
    with np.load(path) as arrays:
        for name in sorted(arrays.files):
            a = arrays[name]
            h.update(name.encode())
            h.update(str(a.dtype).encode() + str(a.shape).encode())
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def read_clip(clips_dir: Path, clip_id: str) -> tuple[ClipEntry, dict[str, np.ndarray]]:
    """One clip of the set in ``clips_dir``: its manifest entry and its arrays (:data:`CLIP_ARRAYS`, shapes
    checked against each other and the entry); every problem is a :class:`ManifestError`."""
    manifest = read_clip_manifest(clips_dir)
    entry = next((c for c in manifest.clips if c.id == clip_id), None)
    if entry is None:
        raise ManifestError(f"the clip set in {clips_dir} has no clip {clip_id!r}; it has "
                            f"{', '.join(c.id for c in manifest.clips)}")
    path = entry.path
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [name for name in CLIP_ARRAYS if name not in z.files]
            arrays = {name: z[name] for name in CLIP_ARRAYS if name in z.files}
    except FileNotFoundError:
        raise ManifestError(f"{path} is missing; rebuild the clip set with `animstudy clips build`") from None
    except (OSError, ValueError, EOFError) as exc:
        raise ManifestError(f"{path} is unreadable ({exc}); rebuild the clip set with `animstudy clips build`"
                            ) from None
    if missing:
        raise ManifestError(f"{path} lacks {', '.join(missing)}; rebuild the clip set with `animstudy clips build`")
    j = arrays["joint_names"].shape[0]
    shapes = {"parents": (j,), "offsets": (j, 3), "bind_rotations": (j, 4), "bind_positions": (j, 3),
              "times": (entry.frames,), "local_rotations": (entry.frames, j, 4), "root_positions": (entry.frames, 3),
              "world_rotations": (entry.frames, j, 4), "world_positions": (entry.frames, j, 3)}
    for name, shape in shapes.items():
        if arrays[name].shape != shape:
            raise ManifestError(f"{path}: {name} has shape {arrays[name].shape}, expected {shape} for {j} joints "
                                f"and {entry.frames} frames; rebuild the clip set with `animstudy clips build`")
    return entry, arrays
