"""H.264 MP4 files (yuv420p, fast start) and JPEG posters, with nothing in them that names their content."""

from __future__ import annotations

import os
import threading
from fractions import Fraction
from pathlib import Path
from types import TracebackType

import av
import numpy as np
from av.video.reformatter import VideoReformatter
from numpy.typing import NDArray
from PIL import Image

CRF = 20
PRESET = "veryfast"
# Every media file gets this access and modification time (2000-01-01T00:00:00Z): the order and the moment in
# which files were written (the hybrid-left video of a pair just before the hybrid-right one, increment 0 before
# increment 1) must not be readable from them, over HTTP or off the disk.
FILE_TIME = 946_684_800


def publish(tmp: Path, path: Path) -> None:
    """Move the finished ``tmp`` to ``path`` with the constant :data:`FILE_TIME`."""
    os.utime(tmp, (FILE_TIME, FILE_TIME))
    tmp.replace(path)


Planes = tuple[NDArray[np.uint8], NDArray[np.uint8], NDArray[np.uint8]]
# One reformatter per thread, kept: it keeps its swscale context from frame to frame, where
# ``VideoFrame.reformat`` makes a new one per frame (160x120: 0.49 -> 0.14 ms a frame, the same bytes).
_REFORMATTERS = threading.local()


def yuv420(rgb: NDArray[np.uint8]) -> Planes:
    """The Y ``(H, W)``, U and V ``(H/2, W/2)`` planes the encoder will store for an RGB image (the same
    conversion it would make), so frames can be kept and tiled at half the size and converted once."""
    h, w = rgb.shape[:2]
    reformatter = getattr(_REFORMATTERS, "one", None)
    if reformatter is None:
        reformatter = _REFORMATTERS.one = VideoReformatter()
    packed = reformatter.reformat(av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24"),
                                  format="yuv420p").to_ndarray()
    chroma = packed[h:].reshape(2, h // 2, w // 2)
    return packed[:h], chroma[0], chroma[1]


def _pack(planes: Planes) -> NDArray[np.uint8]:
    y, u, v = planes
    return np.concatenate([y, u.reshape(-1, y.shape[1]), v.reshape(-1, y.shape[1])])


def hstack_planes(*images: Planes) -> Planes:
    """Images side by side, plane by plane (every width even, so the chroma planes line up)."""
    return tuple(np.concatenate([im[k] for im in images], axis=1) for k in range(3))  # type: ignore[return-value]


class VideoWriter:
    """Writes RGB frames ``(H, W, 3)`` uint8 to an MP4 file; the file appears under its name only when complete.

    One encoder thread: encoding is parallelised across processes, and a single-threaded x264 is deterministic.
    """

    def __init__(self, path: Path, width: int, height: int, fps: int) -> None:
        if width % 2 or height % 2:
            raise ValueError(f"yuv420p needs even dimensions, got {width}x{height}")
        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        self._container = av.open(str(self._tmp), mode="w", format="mp4", options={"movflags": "+faststart"})
        self._stream = self._container.add_stream("libx264", rate=Fraction(fps))
        self._stream.width, self._stream.height = width, height
        self._stream.pix_fmt = "yuv420p"
        self._stream.codec_context.time_base = Fraction(1, fps)
        # A short lookahead: a third less encoder memory and smaller files for these short, static-camera loops.
        # No macroblock tree: with it, the render pipeline wrote different files for identical pictures from run
        # to run (6 of 8 videos of one animation); without it they are byte-identical.
        self._stream.codec_context.options = {"crf": str(CRF), "preset": PRESET, "threads": "1",
                                              "x264-params": "rc-lookahead=5:mbtree=0"}
        self._frames = 0

    def write(self, image: NDArray[np.uint8] | Planes) -> None:
        """Append a frame: RGB ``(H, W, 3)`` or YUV 4:2:0 planes from :func:`yuv420`."""
        if isinstance(image, tuple):
            frame = av.VideoFrame.from_ndarray(_pack(image), format="yuv420p")
        else:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
        frame.pts = self._frames
        frame.time_base = self._stream.codec_context.time_base
        self._container.mux(self._stream.encode(frame))
        self._frames += 1

    def close(self) -> None:
        self._container.mux(self._stream.encode(None))
        self._container.close()
        publish(self._tmp, self.path)

    def abort(self) -> None:
        self._container.close()
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_poster(path: Path, rgb: NDArray[np.uint8]) -> None:
    """A JPEG still (no EXIF or comments)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    Image.fromarray(rgb).save(tmp, format="JPEG", quality=88)
    publish(tmp, path)


def probe(path: Path) -> dict:
    """Frame count, frame rate, size, codec, pixel format and all metadata tags of a video file."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = sum(1 for _ in container.decode(stream))
        return {"frames": frames, "fps": float(stream.average_rate), "width": stream.width, "height": stream.height,
                "codec": stream.codec_context.name, "pix_fmt": stream.codec_context.pix_fmt,
                "metadata": {**container.metadata, **stream.metadata}}


def decode(path: Path) -> NDArray[np.uint8]:
    """All frames ``(T, H, W, 3)`` of a video as RGB."""
    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])
