"""Test meshes for the solid: `make_fish_mesh` at a coarse resolution for the physics tests, and
`profile_mesh`, a tiny independent triangulation of the docs/physics.md section 2 profile built with
`triangle`, for the finite-difference gradient checks (48 nodes: fast and well resolved by FD).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fishsim.mesh.fish_mesh import ACTUATOR_BOTTOM, ACTUATOR_NONE, ACTUATOR_TOP, FishMesh


def kern_half_width(X: np.ndarray, length: float) -> np.ndarray:
    """Half-width w(X) [m] of the Kern & Koumoutsakos profile, X = 0 at the tail (docs/physics.md 2)."""
    s = length - X
    wh = sb = 0.04 * length
    st, wt = 0.95 * length, 0.01 * length
    head = np.sqrt(np.clip(2 * wh * s - s**2, 0.0, None))
    body = wh - (wh - wt) * ((s - sb) / (st - sb)) ** 2
    tail = wt * (length - s) / (length - st)
    return np.where(s < sb, head, np.where(s < st, body, tail))


def _boundary_loop(triangles: np.ndarray) -> np.ndarray:
    """Counter-clockwise boundary node loop of a ccw triangulation (edges used by one triangle)."""
    edges = np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]])
    key = np.sort(edges, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = edges[counts[inverse.ravel()] == 1]
    nxt = dict(zip(boundary[:, 0].tolist(), boundary[:, 1].tolist()))
    loop = [int(boundary[0, 0])]
    while len(loop) < len(boundary):
        loop.append(nxt[loop[-1]])
    return np.asarray(loop, dtype=np.int64)


def profile_mesh(length: float = 0.2, edge_length: float = 4e-3, muscle_every: int = 2) -> FishMesh:
    """Triangulated fish profile with every `muscle_every`-th surface element (centroid X in
    [0.05 L, 0.9 L]) marked as a muscle, top (Y > 0) or bottom (Y < 0)."""
    import triangle

    n_side = max(8, int(np.ceil(length / edge_length)))
    X = length * (1 - np.cos(np.linspace(0, np.pi, n_side + 1))) / 2
    w = kern_half_width(X, length)
    bottom = np.stack([X, -w], 1)[:-1]                       # tail -> head along the bottom
    top = np.stack([X[::-1], w[::-1]], 1)[:-1]               # head -> tail along the top
    pts = np.concatenate([bottom, top])                       # counter-clockwise outline
    segs = np.stack([np.arange(len(pts)), (np.arange(len(pts)) + 1) % len(pts)], 1)
    area = (np.sqrt(3) / 4) * edge_length**2
    out = triangle.triangulate({"vertices": pts, "segments": segs}, f"pq30a{area:.3e}")
    points = out["vertices"].astype(np.float64)
    tris = out["triangles"].astype(np.int64)
    d1, d2 = points[tris[:, 1]] - points[tris[:, 0]], points[tris[:, 2]] - points[tris[:, 0]]
    flip = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0] < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    surface = _boundary_loop(tris)
    on_surface = np.zeros(len(points), bool)
    on_surface[surface] = True
    centroid = points[tris].mean(1)
    candidates = np.flatnonzero(on_surface[tris].sum(1) >= 2)
    candidates = candidates[(centroid[candidates, 0] > 0.05 * length) & (centroid[candidates, 0] < 0.9 * length)]
    actuator = np.full(len(tris), ACTUATOR_NONE, np.int8)
    for side, sign in ((ACTUATOR_TOP, 1), (ACTUATOR_BOTTOM, -1)):
        group = candidates[np.sign(centroid[candidates, 1]) == sign]
        group = group[np.argsort(centroid[group, 0])][::muscle_every]
        actuator[group] = side
    return FishMesh(points, tris, surface, actuator, float(length))


@pytest.fixture(scope="session")
def tiny_mesh() -> FishMesh:
    """~60-node fish for finite-difference gradient checks."""
    return profile_mesh(edge_length=1.5e-2, muscle_every=1)


@pytest.fixture(scope="session")
def coarse_mesh() -> FishMesh:
    """The project's fish mesher at 5 mm edges, uniform (the paper's mesh, on which its station
    muscles are calibrated: 257 nodes, 33 muscles) for the physics tests."""
    from fishsim.mesh import make_fish_mesh

    return make_fish_mesh(edge_length=5e-3, actuator_spacing=1e-2, elements_across=2)


@pytest.fixture(autouse=True)
def _float64_default():
    """The solid runs in float64; restore the default so other tests in this worker keep theirs."""
    before = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(before)
