"""One reusable matplotlib (Agg) figure for trajectory frames: a panel per run, each with the
colour-mapped fluid field, the fish mesh, the fluid-to-solid force arrows and a time stamp,
plus one shared colour bar.  ``update(t)`` only changes artists' data, so rendering hundreds
of frames costs one Agg draw each, not a new figure.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from fishsim.render.config import RenderConfig
from fishsim.render.data import RenderData
from fishsim.render.fields import (
    COLORMAPS,
    UNITS,
    arrow_forces,
    colour_limits,
    field_frames,
    force_scale,
    normalised,
)

FISH_FACE, FISH_EDGE, ARROW = "0.3", "0.08", "red"
MARGIN = {"left": 62, "gap": 62, "top": 46, "bottom": 44, "cbar": 112, "no_cbar": 24}  # pixels


def round16(n: float) -> int:
    """Round up to a multiple of 16 pixels (what video codecs want)."""
    return int(16 * math.ceil(n / 16))


def follow_window(data: RenderData, window: float) -> tuple[float, float]:
    """Width and height (m) of the zoom window: ``window`` (0 = 3 fish lengths), capped by the
    view extent in each direction."""
    x0, x1, y0, y1 = data.extent()
    w = window or 3.0 * data.fish_length
    return min(w, x1 - x0), min(w, y1 - y0)


def follow_limits(data: RenderData, t: int, size: tuple[float, float]) -> tuple[tuple, tuple]:
    """x and y limits of a window of ``size`` centred on the fish centroid at frame t, shifted
    to stay inside the view extent."""
    x0, x1, y0, y1 = data.extent()
    c = data.q[t].mean(axis=0)
    lx = float(np.clip(c[0] - size[0] / 2, x0, x1 - size[0]))
    ly = float(np.clip(c[1] - size[1] / 2, y0, y1 - size[1]))
    return (lx, lx + size[0]), (ly, ly + size[1])


class Panel:
    """One run drawn in one axes; ``update(t)`` moves the fish, arrows, field and time stamp."""

    def __init__(self, ax, data: RenderData, frames: np.ndarray | None, clim, cmap: str,
                 cfg: RenderConfig, f_scale: float, window: tuple[float, float] | None,
                 arrows: tuple[np.ndarray, np.ndarray]):
        self.ax, self.data, self.frames, self.cfg, self.window = ax, data, frames, cfg, window
        self.anchor, self.forces = arrows     # ``arrow_forces`` of the run: anchor nodes, forces
        x0, x1, y0, y1 = data.extent()
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_facecolor("#eef2f6")
        self.image = None
        if frames is not None:
            self.image = ax.imshow(frames[0], origin="lower", extent=(x0, x1, y0, y1), cmap=cmap,
                                   vmin=clim[0], vmax=clim[1], interpolation="bilinear", aspect="auto")
        self.fish = PolyCollection(self._verts(0), facecolors=FISH_FACE, edgecolors=FISH_EDGE,
                                   linewidths=0.25, zorder=2)
        ax.add_collection(self.fish)
        self.arrows = self._quiver(f_scale)
        self.stamp = ax.text(0.01, 0.97, "", transform=ax.transAxes, va="top", ha="left", fontsize=9,
                             zorder=4, bbox={"boxstyle": "round,pad=0.25", "fc": "white", "ec": "none", "alpha": 0.8})

    def _verts(self, t: int) -> np.ndarray:
        return self.data.q[t][self.data.triangles]

    def _quiver(self, f_scale: float):
        """Red force arrows ending on the surface nodes they push (fluid to solid); a force of
        f_scale is drawn ``arrow_length`` metres long."""
        if not self.cfg.arrows or f_scale <= 0:
            return None
        length = self.cfg.arrow_length or 0.12 * self.data.fish_length
        q, f = self.data.q[0, self.anchor], self.forces[0]
        return self.ax.quiver(q[:, 0], q[:, 1], f[:, 0], f[:, 1], color=ARROW, angles="xy",
                              scale_units="xy", scale=f_scale / length, pivot="tip", width=0.0015,
                              alpha=0.8, zorder=3)

    def dynamic_artists(self) -> list:
        """What changes from frame to frame, in drawing order (spines redrawn over the image)."""
        arts = [self.image, self.fish, self.arrows, *self.ax.spines.values(), self.stamp]
        return [a for a in arts if a is not None]

    def update(self, t: int) -> None:
        """Show frame t (the field from the latest stored fluid frame <= t)."""
        d = self.data
        self.fish.set_verts(self._verts(t))
        if self.arrows is not None:
            self.arrows.set_offsets(d.q[t, self.anchor])
            self.arrows.set_UVC(self.forces[t, :, 0], self.forces[t, :, 1])
        k = d.fluid_index(t) if self.image is not None else None
        if self.image is not None:
            self.image.set_visible(k is not None)
            if k is not None:
                self.image.set_data(self.frames[k])
        stale = "" if k is None or d.fluid_frame[k] == t else f"  (fluid of frame {d.fluid_frame[k]})"
        self.stamp.set_text(f"t = {d.time[t]:.3f} s   frame {t}{stale}")
        if self.window is not None:
            xlim, ylim = follow_limits(d, t, self.window)
            self.ax.set_xlim(*xlim)
            self.ax.set_ylim(*ylim)


class FrameFigure:
    """The figure for a run (one panel) or a comparison (one panel per run, same colour limits).

    Attributes for callers and tests: ``fig``, ``panels``, ``clim`` (the colour limits),
    ``colorbar`` (None in vacuum), ``title``, ``size`` (width, height) in pixels.
    """

    def __init__(self, runs: Sequence[RenderData], cfg: RenderConfig, labels: Sequence[str] = ()):
        self.cfg = cfg
        self.runs = list(runs)
        self.labels = list(labels) or [r.name for r in self.runs]
        frames = [self._frames(r) for r in self.runs]
        self.clim = self._limits(frames)
        window = follow_window(self.runs[0], cfg.window) if cfg.follow else None
        has_cbar = any(f is not None for f in frames)
        self.size, axes_boxes, cbar_box = self._layout(window, has_cbar)
        self.fig = Figure(figsize=(self.size[0] / cfg.dpi, self.size[1] / cfg.dpi), dpi=cfg.dpi)
        FigureCanvasAgg(self.fig)
        arrows = [arrow_forces(r.f_ext, r.surface, cfg.arrow_count) for r in self.runs]
        f_scale = max(force_scale(forces) for _, forces in arrows)
        cmap = COLORMAPS[cfg.field]
        self.panels = [Panel(self.fig.add_axes(box), r, f, self.clim, cmap, cfg, f_scale, window, a)
                       for box, r, f, a in zip(axes_boxes, self.runs, frames, arrows)]
        self.colorbar = self._colorbar(cbar_box) if has_cbar else None
        self._dynamic = [a for p in self.panels for a in p.dynamic_artists()]
        self._background = None
        self.title = self._title()
        self.fig.suptitle(self.title, fontsize=11)
        if len(self.panels) > 1:
            for p, label in zip(self.panels, self.labels):
                p.ax.set_title(label + ("" if p.data.complete else " (incomplete)"), fontsize=10)

    def _frames(self, run: RenderData) -> np.ndarray | None:
        if not run.has_fluid:
            return None
        frames = field_frames(run, self.cfg.field)
        return normalised(frames) if self.cfg.normalize else frames

    def _limits(self, frames: list) -> tuple[float, float]:
        """Shared fixed colour limits: the widest of the runs' robust limits."""
        if self.cfg.normalize:
            return (-1.0, 1.0) if self.cfg.field != "speed" else (0.0, 1.0)
        lims = [colour_limits(f, self.cfg.field, self.cfg.percentile, r.fluid.get("mask"))
                for r, f in zip(self.runs, frames) if f is not None]
        if not lims:
            return (0.0, 1.0)
        return min(lo for lo, _ in lims), max(hi for _, hi in lims)

    def _layout(self, window, has_cbar: bool):
        """Figure size (px, multiples of 16) and axes boxes (figure fractions) so that every
        panel shows x and y at the same scale."""
        m, n = MARGIN, len(self.runs)
        x0, x1, y0, y1 = self.runs[0].extent()
        w, h = window if window is not None else (x1 - x0, y1 - y0)
        W = round16(self.cfg.width)
        right = m["cbar"] if has_cbar else m["no_cbar"]
        pw = (W - m["left"] - right - m["gap"] * (n - 1)) / n
        ph = pw * h / w
        H = round16(ph + m["top"] + m["bottom"])
        bottom = H - m["top"] - ph
        boxes = [((m["left"] + i * (pw + m["gap"])) / W, bottom / H, pw / W, ph / H) for i in range(n)]
        cbar = ((W - right + 14) / W, bottom / H, 16 / W, ph / H)
        return (W, H), boxes, cbar

    def _colorbar(self, box):
        image = next(p.image for p in self.panels if p.image is not None)
        unit = "normalised" if self.cfg.normalize else UNITS[self.cfg.field]
        return self.fig.colorbar(image, cax=self.fig.add_axes(box), label=f"{self.cfg.field} [{unit}]")

    def _title(self) -> str:
        names = " vs ".join(self.labels)
        incomplete = [r for r in self.runs if not r.complete]
        tail = "" if not incomplete else "  (incomplete: " + ", ".join(
            f"{r.n_frames} frames" for r in incomplete) + ")"
        vacuum = "" if any(r.has_fluid for r in self.runs) else " (no fluid stored)"
        return f"{names}: {self.cfg.field}{vacuum}, sample {self.cfg.sample}{tail}"

    def update(self, t: int) -> None:
        """Show frame t in every panel."""
        for p in self.panels:
            p.update(min(t, p.data.n_frames - 1))

    def rgb(self) -> np.ndarray:
        """Draw and return the image, uint8 [height, width, 3].

        Blitting: the static parts (axes, ticks, labels, colour bar, title) are drawn once and
        kept as a background; each frame restores it and draws only the changing artists.  A
        following zoom changes the ticks, so it redraws the static parts every frame."""
        canvas = self.fig.canvas
        if self._background is None or self.cfg.follow:
            for a in self._dynamic:
                a.set_animated(True)
            canvas.draw()
            self._background = canvas.copy_from_bbox(self.fig.bbox)
        canvas.restore_region(self._background)
        for p in self.panels:
            for a in p.dynamic_artists():
                if a.get_visible():
                    p.ax.draw_artist(a)
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()

    def data_to_pixel(self, panel: int, xy: np.ndarray) -> np.ndarray:
        """Image pixel coordinates (column, row from the top) of data points [n,2] in a panel."""
        disp = self.panels[panel].ax.transData.transform(np.asarray(xy, float))
        return np.column_stack([disp[:, 0], self.size[1] - disp[:, 1]])
