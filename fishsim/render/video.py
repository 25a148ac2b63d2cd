"""Frames to files: PNG per frame, and a video written as frames arrive (MP4 through
imageio-ffmpeg, GIF when ffmpeg is missing or was asked for)."""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np
from PIL import Image


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write an uint8 [H, W, 3] image as PNG (fast zlib level: frames are many)."""
    Image.fromarray(rgb).save(path, compress_level=1)


def ffmpeg_available() -> bool:
    """Whether imageio-ffmpeg can find an ffmpeg executable."""
    try:
        import imageio_ffmpeg

        return bool(imageio_ffmpeg.get_ffmpeg_exe())
    except Exception:  # noqa: BLE001 - any failure means: no ffmpeg
        return False


class VideoWriter:
    """Append frames to ``<stem>.mp4`` (or ``.gif``); ``path`` is the file actually written."""

    def __init__(self, stem: Path, fmt: str, fps: int):
        self.fmt = "mp4" if fmt == "mp4" and ffmpeg_available() else "gif"
        self.path = Path(stem).with_suffix("." + self.fmt)
        self.frames = 0
        if self.fmt == "mp4":
            self._writer = imageio.get_writer(self.path, format="FFMPEG", fps=fps, codec="libx264",
                                              quality=7, pixelformat="yuv420p", macro_block_size=16,
                                              ffmpeg_log_level="error")
        else:
            self._writer = imageio.get_writer(self.path, mode="I", duration=1000.0 / fps, loop=0)

    def append(self, rgb: np.ndarray) -> None:
        self._writer.append_data(rgb)
        self.frames += 1

    def close(self) -> None:
        self._writer.close()
