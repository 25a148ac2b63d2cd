"""``fishsim render`` settings: one plain dataclass, every field with a default.

The lead's structured config (``fishsim/config.py``) can use ``RenderConfig`` as the schema of
the ``render`` command directly; ``validate`` raises ``ConfigError`` with one line.
"""

from __future__ import annotations

import dataclasses

from fishsim.errors import ConfigError

FIELDS = ("pressure", "vorticity", "speed")
VIDEO_FORMATS = ("mp4", "gif", "none")


@dataclasses.dataclass
class RenderConfig:
    """What to render and how.

    path: a trajectory file (``.h5``) or a folder (every ``*.h5`` inside is rendered).
    compare: a second trajectory drawn side by side (same colour limits), plus an overlay of the
        two normalised pressure fields; ``labels`` names the panels (default: file names).
    field: the colour-mapped fluid field: pressure (Pa), vorticity (1/s) or speed (m/s).
    sample: the batch index b of ``/solid/q[t, b]``.
    start, stop, stride: the frames rendered, ``range(start, stop, stride)``; stop < 0 = all;
        stride null (default): the frames whose fluid was stored (no frame shows a stale fluid).
    width, dpi: image width in pixels, rounded up to a multiple of 16 for video codecs (the
        height follows the view's aspect ratio, x and y at the same scale); resolution.
    follow, window: zoom on a window of ``window`` metres (0 = 3 fish lengths) that follows the
        fish centroid.
    percentile: colour limits are this percentile of |field| over the whole run (robust).
    normalize: divide the field of every frame by its max |value| (limits -1..1).
    arrows, arrow_length, arrow_count: draw f_ext as about ``arrow_count`` arrows along the
        surface, each the total force on its run of consecutive surface nodes (0: one per node);
        the run's 95th-percentile arrow is drawn ``arrow_length`` metres long (0 = 0.12 fish
        lengths).
    video, fps: mp4 (falls back to gif without ffmpeg), gif or none; frames per second.
    pngs: write one PNG per rendered frame.
    overlay_frame: the frame of the comparison overlay (-1 = last frame with fluid in both).
    vtk: also write a ParaView series (fish .vtu, fluid .vti, .pvd collections).
    progress: show a progress bar.
    """

    path: str = ""
    compare: str = ""
    labels: list[str] = dataclasses.field(default_factory=list)
    field: str = "pressure"
    sample: int = 0
    start: int = 0
    stop: int = -1
    stride: int | None = None
    width: int = 1200
    dpi: int = 100
    follow: bool = False
    window: float = 0.0
    percentile: float = 99.0
    normalize: bool = False
    arrows: bool = True
    arrow_length: float = 0.0
    arrow_count: int = 40
    video: str = "mp4"
    fps: int = 20
    pngs: bool = True
    overlay_frame: int = -1
    vtk: bool = False
    progress: bool = True
    out_dir: str | None = None

    def validate(self) -> None:
        """Raise ConfigError (one line) for a value that cannot work."""
        _require(bool(self.path), "render needs a trajectory: path=run.h5 (or a folder of .h5 files)")
        _require(self.field in FIELDS, f"field must be one of {', '.join(FIELDS)} (got '{self.field}')")
        _require(self.video in VIDEO_FORMATS,
                 f"video must be one of {', '.join(VIDEO_FORMATS)} (got '{self.video}')")
        _require(self.stride is None or self.stride >= 1, f"stride must be >= 1 or null (got {self.stride})")
        _require(self.start >= 0, f"start must be >= 0 (got {self.start})")
        _require(self.sample >= 0, f"sample must be >= 0 (got {self.sample})")
        _require(self.width >= 160, f"width must be >= 160 pixels (got {self.width})")
        _require(self.dpi > 0 and self.fps > 0, "dpi and fps must be > 0")
        _require(0 < self.percentile <= 100, f"percentile must be in (0, 100] (got {self.percentile})")
        _require(self.window >= 0 and self.arrow_length >= 0 and self.arrow_count >= 0,
                 "window, arrow_length and arrow_count must be >= 0")


def _require(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)
