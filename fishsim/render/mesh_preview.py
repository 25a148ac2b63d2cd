"""Preview picture of a fish mesh (paper Fig. 9): elements, actuator groups, surface polyline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from fishsim.mesh.fish_mesh import ACTUATOR_BOTTOM, ACTUATOR_TOP, FishMesh
from fishsim.mesh.triangulate import element_angles

#: Face colours per actuator id: none, top (red), bottom (light blue), as in paper Fig. 9.
FACE_COLORS = ("#f2f2f2", "#d62728", "#8ecae6")
EDGE_COLOR = "#7f7f7f"
SURFACE_COLOR = "black"


def plot_mesh(mesh: FishMesh, path, title: str | None = None, dpi: int = 150) -> Path:
    """Write a PNG of the mesh to `path` (headless Agg) and return the path: every element
    outlined, top actuated elements red, bottom light blue, the surface polyline in black,
    axes in mm with equal scale, a legend with the counts and the minimum angle."""
    width, height = np.ptp(mesh.points, axis=0)
    fig = Figure(figsize=(10, 1.6 + 10 * height / width), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    _draw_elements(ax, mesh)
    _draw_surface(ax, mesh)
    ax.set_aspect("equal")
    ax.set_xlabel("X [mm] (tail at 0, head at L)")
    ax.set_ylabel("Y [mm]")
    ax.set_title(title or f"fish mesh, L = {mesh.length * 1e3:g} mm")
    fig.legend(handles=_legend_handles(mesh), loc="outside lower center", ncols=3, fontsize=8)
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
