"""Preview picture of a fish mesh (paper Fig. 9): elements, muscles, surface polyline.

The muscles are either the mesher's actuator stations (the paper's model, ``fish.muscles=paper``:
whole elements, top red, bottom light blue) or, given ``layer=(thickness, x_range)``, the
default muscle layer (fishsim/solid/muscles.py): each element shaded by its area fraction inside
the top (red) and bottom (blue) layers, and the layers' inner edges drawn dashed.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from fishsim.mesh.fish_mesh import ACTUATOR_BOTTOM, ACTUATOR_TOP, FishMesh
from fishsim.mesh.triangulate import element_angles, element_areas

#: Face colours per actuator id: none, top (red), bottom (light blue), as in paper Fig. 9.
FACE_COLORS = ("#f2f2f2", "#d62728", "#8ecae6")
#: Full-fraction colours of the muscle layer: top (red), bottom (blue).
LAYER_COLORS = ("#d62728", "#1f77b4")
EDGE_COLOR = "#7f7f7f"
SURFACE_COLOR = "black"


def plot_mesh(mesh: FishMesh, path, title: str | None = None, dpi: int = 150,
              layer: tuple[float, Sequence[float]] | None = None) -> Path:
    """Write a PNG of the mesh to `path` (headless Agg) and return the path: every element
    outlined, the muscles coloured (module docstring: the stations, or the muscle layer of
    ``layer`` = (thickness, x_range) with its area fractions), the surface polyline in black,
    axes in mm with equal scale, a legend with the counts and the minimum angle."""
    width, height = np.ptp(mesh.points, axis=0)
    fig = Figure(figsize=(10, 1.6 + 10 * height / width), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    if layer is None:
        _draw_elements(ax, mesh)
        handles = _legend_handles(mesh)
    else:
        handles = _draw_layer(ax, mesh, *layer)
    _draw_surface(ax, mesh)
    ax.set_aspect("equal")
    ax.set_xlabel("X [mm] (tail at 0, head at L)")
    ax.set_ylabel("Y [mm]")
    ax.set_title(title or f"fish mesh, L = {mesh.length * 1e3:g} mm")
    fig.legend(handles=handles, loc="outside lower center", ncols=3, fontsize=8)
    ax.margins(0.02, 0.1)
    path = Path(path)
    fig.savefig(path)
    return path


def _draw_elements(ax, mesh: FishMesh) -> None:
    """All triangles as one PolyCollection, coloured by actuator id (coordinates in mm)."""
    faces = np.asarray(FACE_COLORS)[mesh.actuator]
    polys = PolyCollection(1e3 * mesh.points[mesh.triangles], facecolors=faces,
                           edgecolors=EDGE_COLOR, linewidths=0.2)
    ax.add_collection(polys)
    ax.autoscale_view()


def _draw_layer(ax, mesh: FishMesh, thickness: float, x_range: Sequence[float]) -> list:
    """The muscle layer: faces blended from grey towards red by the top fraction and towards blue
    by the bottom fraction, the layers' inner edges Y = w_top - t b and w_bot + t b dashed
    between x_range; returns the legend handles (element counts, muscle areas)."""
    import torch

    from fishsim.solid.muscles import layer_fractions, surface_half_widths

    f_top, f_bot = (f.numpy() for f in layer_fractions(mesh, torch.tensor(float(thickness)), tuple(x_range)))
    rgb = lambda c: np.array([int(c[k:k + 2], 16) / 255 for k in (1, 3, 5)])
    base, top, bottom = rgb(FACE_COLORS[0]), rgb(LAYER_COLORS[0]), rgb(LAYER_COLORS[1])
    f_top, f_bot = np.clip(f_top, 0, 1), np.clip(f_bot, 0, 1)
    rest = np.clip(1 - f_top - f_bot, 0, 1)
    faces = rest[:, None] * base + f_top[:, None] * top + f_bot[:, None] * bottom
    polys = PolyCollection(1e3 * mesh.points[mesh.triangles], facecolors=faces,
                           edgecolors=EDGE_COLOR, linewidths=0.2)
    ax.add_collection(polys)
    ax.autoscale_view()
    X = np.linspace(x_range[0], x_range[1], 400) * mesh.length
    w_top, w_bot = surface_half_widths(mesh, X)
    half = 0.5 * (w_top - w_bot)
    for inner in (w_top - thickness * half, w_bot + thickness * half):
        ax.plot(1e3 * X, 1e3 * inner, color="black", linewidth=0.6, linestyle="--")
    area = np.abs(element_areas(mesh.points, mesh.triangles))
    min_angle = float(element_angles(mesh.points, mesh.triangles).min())
    label = lambda side, f: f"{side} layer: {int(np.sum(f > 1e-9))} elements, {1e6 * float(np.sum(f * area)):.0f} mm$^2$"
    return [
        Patch(facecolor=LAYER_COLORS[0], label=label("top", f_top)),
        Patch(facecolor=LAYER_COLORS[1], label=label("bottom", f_bot)),
        Patch(facecolor=FACE_COLORS[0], edgecolor=EDGE_COLOR,
              label=f"{mesh.n_elements} elements, {mesh.n_nodes} nodes, min angle {min_angle:.1f} deg"),
    ]


def _draw_surface(ax, mesh: FishMesh) -> None:
    """The closed surface polyline (mm)."""
    loop = 1e3 * mesh.points[np.append(mesh.surface, mesh.surface[0])]
    ax.plot(loop[:, 0], loop[:, 1], color=SURFACE_COLOR, linewidth=0.8)


def _legend_handles(mesh: FishMesh) -> list:
    """Legend proxies: the two actuator groups with counts, and the mesh summary."""
    min_angle = float(element_angles(mesh.points, mesh.triangles).min())
    n_top = int(np.sum(mesh.actuator == ACTUATOR_TOP))
    n_bottom = int(np.sum(mesh.actuator == ACTUATOR_BOTTOM))
    return [
        Patch(facecolor=FACE_COLORS[ACTUATOR_TOP], label=f"top actuated: {n_top}"),
        Patch(facecolor=FACE_COLORS[ACTUATOR_BOTTOM], label=f"bottom actuated: {n_bottom}"),
        Patch(facecolor=FACE_COLORS[0], edgecolor=EDGE_COLOR,
              label=f"{mesh.n_elements} elements, {mesh.n_nodes} nodes, min angle {min_angle:.1f} deg"),
    ]
