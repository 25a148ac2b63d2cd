"""Two runs at one frame, as in the paper's appendix: the normalised pressure fields side by
side (each divided by its max |p|, both on -1..1), and an overlay of the two normalised fields
as contours (first run red, second blue; solid lines p > 0, dashed p < 0) with both fish outlines.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from fishsim.errors import InputFileError
from fishsim.render.data import RenderData
from fishsim.render.fields import normalised

LEVELS = [-0.9, -0.7, -0.5, -0.3, -0.1, 0.1, 0.3, 0.5, 0.7, 0.9]
COLOURS = ("tab:red", "tab:blue")


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """Edges [E,2] that belong to exactly one triangle: the outline of the mesh."""
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return unique[counts == 1]


def common_fluid_frame(runs: Sequence[RenderData], frame: int = -1) -> int:
    """The requested frame, or (frame < 0) the last frame index stored with fluid in every run."""
    if not all(r.has_fluid for r in runs):
        raise InputFileError("the comparison overlay needs stored pressure in both trajectories")
    if frame >= 0:
        return frame
    shared = shared_fluid_frames(runs)
    return max(shared) if shared else min(int(r.fluid_frame[-1]) for r in runs)


def shared_fluid_frames(runs: Sequence[RenderData]) -> list[int] | None:
    """The frame indices stored with fluid in every run, sorted (None if a run has no fluid)."""
    if not all(r.has_fluid for r in runs):
        return None
    shared = set(runs[0].fluid_frame.tolist())
    for r in runs[1:]:
        shared &= set(r.fluid_frame.tolist())
    return sorted(shared)


def normalised_pressure(run: RenderData, frame: int) -> np.ndarray:
    """p / max|p| of the latest stored fluid frame <= ``frame``."""
    k = run.fluid_index(min(frame, run.n_frames - 1))
    if k is None:
        raise InputFileError(f"{run.path} has no fluid stored at or before frame {frame}")
    return normalised(run.fluid["p"][k])


def _figure(n_axes: int, run: RenderData, width_in: float = 12.0) -> tuple[Figure, list]:
    x0, x1, y0, y1 = run.extent()
    aspect = (y1 - y0) / (x1 - x0)
    fig = Figure(figsize=(width_in, n_axes * width_in * aspect * 0.9 + 1.0), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = [fig.add_subplot(n_axes, 1, i + 1) for i in range(n_axes)]
    for ax in axes:
        ax.set_aspect("equal")
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
    return fig, axes


def _outline(ax, run: RenderData, frame: int, colour: str) -> None:
    t = min(frame, run.n_frames - 1)
    ax.add_collection(LineCollection(run.q[t][boundary_edges(run.triangles)], colors=colour, linewidths=1.2))


def plot_normalised_fields(runs: Sequence[RenderData], labels: Sequence[str], frame: int, path: Path) -> Path:
    """One panel per run: its pressure divided by its own max |p|, colour limits -1..1."""
    fig, axes = _figure(len(runs), runs[0])
    for ax, run, label in zip(axes, runs, labels):
        H, W, dx = run.grid
        im = ax.imshow(normalised_pressure(run, frame), origin="lower", extent=(0, W * dx, 0, H * dx),
                       cmap="RdBu_r", vmin=-1, vmax=1, interpolation="bilinear")
        _outline(ax, run, frame, "k")
        ax.set_title(f"{label}: normalised pressure, frame {frame}")
    fig.colorbar(im, ax=axes, label="p / max|p|", shrink=0.9)
    fig.savefig(path)
    return path


def plot_overlay(runs: Sequence[RenderData], labels: Sequence[str], frame: int, path: Path) -> Path:
    """Contours of both normalised pressure fields in one axes (red: first, blue: second)."""
    fig, (ax,) = _figure(1, runs[0])
    for run, label, colour in zip(runs, labels, COLOURS):
        H, W, dx = run.grid
        x, y = (np.arange(W) + 0.5) * dx, (np.arange(H) + 0.5) * dx
        ax.contour(x, y, normalised_pressure(run, frame), levels=LEVELS, colors=colour, linewidths=1.0,
                   negative_linestyles="dashed")
        _outline(ax, run, frame, colour)
        ax.plot([], [], color=colour, label=label)
    ax.legend(loc="upper right", fontsize=9)
    ax.set_title(f"overlay of normalised pressure (p / max|p|), frame {frame}; dashed: p < 0")
    fig.savefig(path)
    return path
