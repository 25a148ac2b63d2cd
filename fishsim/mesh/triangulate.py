"""Triangulate the fish profile: outline, quality triangles, surface polyline, actuator groups.

Pipeline of `make_fish_mesh` (docs/physics.md section 2, paper App. A Fig. 9):
  profile w(X) -> closed ccw outline (denser at the round head and the thin tail)
  -> Triangle quality mesh (min angle, max area sqrt(3)/4 h(X)^2 for the graded target edge
  h(X) = clip(2 w(X) / n_across, h/4, h): at least n_across elements across the thin body)
  -> ccw triangles
  -> surface polyline (the boundary edges chained ccw) -> actuator groups (spaced surface
  elements, top Y > 0 and bottom Y < 0).
"""

from __future__ import annotations

import numpy as np
import triangle

from fishsim.errors import ConfigError, MeshError
from fishsim.mesh.fish_mesh import ACTUATOR_BOTTOM, ACTUATOR_NONE, ACTUATOR_TOP, FishMesh
from fishsim.mesh.profile import Profile, check_outline, check_profile, make_profile, polygon_signed_area

#: Triangle terminates reliably for minimum angles up to about 33.8 degrees (Shewchuk).
MAX_MIN_ANGLE = 33.8
#: Largest turning angle (rad) between outline segments: bounds the segment length on curves.
OUTLINE_TURN = np.pi / 16
#: Default elements across the rear body (`graded_edge`): the default fish's tail stroke is then
#: within 1 % of the finest mesh from 3 mm to 1 mm edges (docs/validation.md).
GRADED_ACROSS = 6.0
#: Samples of the fine polyline the outline is resampled from.
N_FINE = 4001
#: Decimals (of a metre) the outline's vertices are rounded to (`snap`): 0.1 nm.
SNAP_DECIMALS = 10


# ---------------------------------------------------------------- outline


def outline_half_width(w: Profile, length: float, tail_tip_width: float) -> Profile:
    """Half-width of the meshed outline: w_out(X) = max(w(X), tail_tip_width / 2) on the tail
    side of the widest point, w(X) elsewhere (metres). The Kern profile tapers to zero width at
    X = 0; this keeps a finite, blunt tail tip so no input angle is sharper than the mesh's
    minimum angle, while keeping X = 0 at the tail and the length L."""
    X = np.linspace(0.0, length, N_FINE)
    x_peak = X[np.argmax(w(X))]
    w_tip = 0.5 * tail_tip_width

    def w_out(X: np.ndarray) -> np.ndarray:
        wX = w(X)
        return np.where(X < x_peak, np.maximum(wX, w_tip), wX)

    return w_out


def graded_edge(w_out: Profile, length: float, edge_length: float, elements_across: float):
    """The target edge h(X) [m] of a body of half-width w_out(X), X in [0, L]: on the tail side of
    the widest point h = clip(2 w(X) / n, h0/4, h0) with n = elements_across and h0 = edge_length,
    so the thin, bending rear body is at least n elements across (linear triangles are too stiff
    in bending when few span the thickness: the cantilever of docs/validation.md is 7.5 % too
    stiff at 4 across, 1.9 % at 8); h0 on the head side. n = 2 grades only the outline (at most
    the half-width), as the ungraded mesher always did."""
    X = np.linspace(0.0, length, N_FINE)
    x_peak = X[np.argmax(w_out(X))]
    n = max(float(elements_across), 2.0)

    def h(X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        thin = np.where(X < x_peak, 2.0 * w_out(X) / n, np.inf)
        return np.clip(thin, 0.25 * edge_length, edge_length)

    return h


def _segment_target(xy: np.ndarray, half_width: np.ndarray, edge_length: float) -> np.ndarray:
    """Target outline segment length h [K] (m) at the fine polyline vertices xy [K, 2]:
    h = clip(min(OUTLINE_TURN / |kappa|, half_width), edge/4, edge), so segments shorten on the
    curved head (curvature kappa, 1/m) and where the body is thin (pass inf to ignore width;
    a graded mesh passes its target edge h(X) here)."""
    d = np.diff(xy, axis=0)
    ds = np.linalg.norm(d, axis=1)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    kappa = np.zeros(len(xy))
    kappa[1:-1] = np.abs(np.diff(heading)) / np.maximum(0.5 * (ds[1:] + ds[:-1]), 1e-300)
    kappa[0], kappa[-1] = kappa[1], kappa[-2]
    h_curve = OUTLINE_TURN / np.maximum(kappa, 1e-300)
    return np.clip(np.minimum(h_curve, half_width), 0.25 * edge_length, edge_length)


def _top_stations(w_out: Profile, length: float, edge_length: float, n_top: int | None,
                  elements_across: float = 2.0) -> np.ndarray:
    """X [n_top + 1] (m) of the top outline vertices, from the head X = L down to the tail X = 0,
    spaced by the local target length (`_segment_target`), or n_top segments if given."""
    u = np.linspace(0.0, 1.0, N_FINE)
    X = 0.5 * length * (1.0 + np.cos(np.pi * u))  # head -> tail, clustered at both ends
    wX = w_out(X)
    xy = np.stack([X, wX], axis=1)
    thin = graded_edge(w_out, length, edge_length, elements_across)(X)  # thin tail side only
    h = _segment_target(xy, thin, edge_length)
    ds = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    n_cum = np.concatenate([[0.0], np.cumsum(ds * 0.5 * (1.0 / h[1:] + 1.0 / h[:-1]))])
    n = max(int(np.ceil(n_cum[-1])), 4) if n_top is None else max(int(n_top), 4)
    return np.interp(np.linspace(0.0, n_cum[-1], n + 1), n_cum, X)


def _end_points(x: float, half_width: float, h: float, top_to_bottom: bool) -> np.ndarray:
    """Interior points [k, 2] of the straight end segment X = x, |Y| <= half_width (m), spaced
    <= h, ordered top -> bottom (tail) or bottom -> top (head)."""
    if half_width <= 0.0:
        return np.zeros((0, 2))
    k = max(int(np.ceil(2.0 * half_width / h)), 1)
    y = np.linspace(half_width, -half_width, k + 1)[1:-1]
    y = y if top_to_bottom else y[::-1]
    return np.stack([np.full_like(y, x), y], axis=1)


def sample_outline(w_out: Profile, length: float, edge_length: float,
                   n_outline: int | None = None, elements_across: float = 2.0) -> np.ndarray:
    """Closed counter-clockwise outline xy [M, 2] (m) of |Y| <= w_out(X), X in [0, L]:
    bottom half tail -> head, head end (a point nose if w_out(L) ~ 0), top half head -> tail,
    then the blunt tail end X = 0. Mirror-symmetric about Y = 0. n_outline, if given, sets
    roughly the number of points M; segments follow `graded_edge` otherwise."""
    tol = 1e-9 * length
    w_tail, w_head = float(w_out(np.array([0.0]))[0]), float(w_out(np.array([length]))[0])
    h_tail = float(graded_edge(w_out, length, edge_length, elements_across)(np.array([0.0]))[0])
    h_head = min(edge_length, max(w_head, 0.25 * edge_length))
    tail = _end_points(0.0, w_tail if w_tail > tol else 0.0, h_tail, top_to_bottom=True)
    head = _end_points(length, w_head if w_head > tol else 0.0, h_head, top_to_bottom=False)
    n_top = None if n_outline is None else (int(n_outline) - len(tail) - len(head)) // 2
    X = _top_stations(w_out, length, edge_length, n_top, elements_across)
    top = np.stack([X, w_out(X)], axis=1)
    top[np.abs(top[:, 1]) <= tol, 1] = 0.0
    bottom = top[::-1] * np.array([1.0, -1.0])
    if top[0, 1] == 0.0:  # point nose shared by both halves
        bottom = bottom[:-1]
    if top[-1, 1] == 0.0:  # pointed tail shared by both halves
        bottom = bottom[1:]
    return np.concatenate([bottom, head, top, tail], axis=0)


# ---------------------------------------------------------------- triangles and surface


def element_areas(points, triangles):
    """Signed areas A [..., T] (m^2) of triangles [T, 3] over points [..., N, 2] (numpy arrays or
    torch tensors, optionally batched); A > 0 when ccw: A = ((x1 - x0) x (x2 - x0)) / 2."""
    a, b, c = (points[..., triangles[:, k], :] for k in range(3))
    e1, e2 = b - a, c - a
    return 0.5 * (e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0])


def element_angles(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Interior angles [T, 3] in degrees, angle k at vertex triangles[:, k]."""
    p = points[triangles]
    u = np.roll(p, -1, axis=1) - p  # to the next vertex
    v = np.roll(p, 1, axis=1) - p  # to the previous vertex
    cos = np.sum(u * v, axis=2) / (np.linalg.norm(u, axis=2) * np.linalg.norm(v, axis=2))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def orient_ccw(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """triangles [T, 3] with the clockwise ones flipped (two vertices swapped) to ccw."""
    tri = triangles.copy()
    cw = element_areas(points, tri) < 0.0
    tri[cw] = tri[cw][:, [0, 2, 1]]
    return tri


def edge_list(triangles: np.ndarray) -> np.ndarray:
    """Directed edges [3T, 2] of triangles [T, 3]: (v0 v1), (v1 v2), (v2 v0) per element;
    edge 3t + k belongs to element t."""
    return np.stack([triangles, np.roll(triangles, -1, axis=1)], axis=2).reshape(-1, 2)


def boundary_edges(triangles: np.ndarray) -> np.ndarray:
    """Indices [E] into `edge_list(triangles)` of the edges used by exactly one element; for
    ccw triangles these run ccw around the outer boundary (the body is on their left)."""
    edges = np.sort(edge_list(triangles), axis=1)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    return np.flatnonzero(counts[inverse.ravel()] == 1)


def surface_polyline(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Surface nodes [S] int64: the boundary edges of ccw triangles chained into one closed ccw
    loop, starting at the nose (largest X, then smallest |Y|). MeshError if the boundary is not a
    single loop (a hole, a pinch or a dangling element)."""
    edges = edge_list(triangles)[boundary_edges(triangles)]
    nxt = dict(zip(edges[:, 0].tolist(), edges[:, 1].tolist()))
    if len(nxt) != len(edges):
        raise MeshError("mesh boundary touches itself (a node with two outgoing boundary edges); "
                        "re-mesh with `fishsim mesh`")
    start = int(min(nxt, key=lambda k: (-points[k, 0], abs(points[k, 1]))))
    loop = [start]
    while len(loop) <= len(edges):
        node = nxt[loop[-1]]
        if node == start:
            break
        loop.append(node)
    if len(loop) != len(edges):
        raise MeshError(f"mesh boundary is not one closed loop ({len(loop)} of {len(edges)} boundary "
                        "edges chained); the fish must have no holes: re-mesh with `fishsim mesh`")
    return np.asarray(loop, dtype=np.int64)


def _area_switch(min_angle: float, max_area: float | None = None) -> str:
    """Triangle's quality switches; its parser reads plain decimals only (no exponent)."""
    num = (lambda v: np.format_float_positional(v, precision=8, fractional=False, trim="-"))
    return f"pq{num(min_angle)}" + ("a" if max_area is None else f"a{num(max_area)}") + "Q"


def snap(xy: np.ndarray) -> np.ndarray:
    """xy rounded to SNAP_DECIMALS decimals of a metre (IEEE multiply, rint and divide: the same
    result on every machine; lengths such as 0.2 m stay exact).

    Triangle's quality refinement is chaotic in its input: moving the default outline's vertices
    by 1-2 ulp gives meshes of 1761 to 1787 nodes. The outline is computed with numpy's cos and
    arctan2, whose last bit depends on the CPU (SIMD library on AVX-512, libm elsewhere), so
    without the snap the default fish had 1775 nodes on one machine and 1761 on another, and
    every result moved with it (the 100-frame distance by 0.1 %, its frequency gradient by 5 %).
    Snapped, Triangle sees the same input everywhere (unless a coordinate lies within an ulp of a
    rounding boundary: ~1e-7 per coordinate)."""
    return np.round(np.asarray(xy, dtype=np.float64), SNAP_DECIMALS)


def triangulate_outline(xy: np.ndarray, edge_length: float, min_angle: float, size=None,
                        max_passes: int = 6):
    """Quality triangulation of the closed polygon xy [M, 2] (snapped: `snap`) with Triangle:
    minimum angle `min_angle` (deg), maximum area sqrt(3)/4 edge_length^2 (an equilateral
    triangle of side edge_length). With `size` (a target edge h(X) [m] of the x coordinate,
    e.g. `graded_edge`) the mesh is then refined until every element's area is at most
    sqrt(3)/4 h(X_c)^2 at its centroid X_c (at most max_passes refinements).
    Returns points [N, 2] float64, triangles [T, 3] int64 ccw."""
    m = len(xy)
    segments = np.stack([np.arange(m), (np.arange(m) + 1) % m], axis=1)
    out = triangle.triangulate({"vertices": snap(xy), "segments": segments},
                               _area_switch(min_angle, np.sqrt(3.0) / 4.0 * edge_length**2))
    for _ in range(max_passes if size is not None else 0):
        points, tri = out["vertices"], out["triangles"]
        limit = np.sqrt(3.0) / 4.0 * size(points[tri, 0].mean(axis=1)) ** 2
        if np.all(np.abs(element_areas(points, tri)) <= limit * (1.0 + 1e-9)):
            break
        out = triangle.triangulate({"vertices": points, "segments": out["segments"], "triangles": tri,
                                    "triangle_max_area": limit}, "r" + _area_switch(min_angle))
    points = np.ascontiguousarray(out["vertices"], dtype=np.float64)
    triangles = orient_ccw(points, np.asarray(out["triangles"], dtype=np.int64))
    return points, triangles


# ---------------------------------------------------------------- actuators


def surface_elements(triangles: np.ndarray) -> np.ndarray:
    """Indices of the elements sharing an edge with the surface, sorted, [n]."""
    return np.unique(boundary_edges(triangles) // 3)


def actuator_groups(points: np.ndarray, triangles: np.ndarray, length: float, spacing: float,
                    x_range: tuple[float, float]) -> np.ndarray:
    """Actuator id [T] int8 (0 none, 1 top, 2 bottom; paper Fig. 9).

    Stations X_j = x_range[0] L + j * spacing up to x_range[1] L (m). At each station the
    surface element (sharing an edge with the surface) whose centroid X is nearest is actuated,
    on the top side (all three nodes Y > 0) and on the bottom side (all nodes Y < 0); stations with
    no element within spacing / 2 are skipped. Both sides use the same stations, so the groups are
    mirror images up to the mesh's asymmetry.
    """
    x0, x1 = x_range[0] * length, x_range[1] * length
    stations = np.arange(x0, x1 + 1e-9 * length, spacing)
    candidates = surface_elements(triangles)
    y = points[triangles[candidates], 1]
    x_c = points[triangles[candidates], 0].mean(axis=1)
    in_range = (x_c >= x0) & (x_c <= x1)
    actuator = np.full(len(triangles), ACTUATOR_NONE, dtype=np.int8)
    for group, side in ((ACTUATOR_TOP, np.all(y > 0.0, axis=1)), (ACTUATOR_BOTTOM, np.all(y < 0.0, axis=1))):
        pool = candidates[side & in_range]
        actuator[_nearest_to_stations(x_c[side & in_range], pool, stations, 0.5 * spacing)] = group
    return actuator


def _nearest_to_stations(x: np.ndarray, ids: np.ndarray, stations: np.ndarray, reach: float) -> np.ndarray:
    """Unique ids [k] of the entries of x [n] nearest to each station [m], if within reach."""
    if len(ids) == 0:
        return ids
    dist = np.abs(x[None, :] - stations[:, None])
    best = np.argmin(dist, axis=1)
    ok = dist[np.arange(len(stations)), best] <= reach
    return np.unique(ids[best[ok]])


# ---------------------------------------------------------------- the fish mesh


def make_fish_mesh(length: float = 0.2, profile="kern", poly_coeffs=None, edge_length: float = 2e-3,
                   min_angle: float = 30.0, n_outline: int | None = None,
                   actuator_spacing: float = 4e-3, actuator_x_range: tuple[float, float] = (0.05, 0.95),
                   tail_tip_width: float | None = None,
                   elements_across: float = GRADED_ACROSS) -> FishMesh:
    """Triangulated fish of length L in its material frame (docs/physics.md section 2).

    length: L in metres (X = 0 tail, X = L head).
    profile: "kern" (Kern & Koumoutsakos 2006), "polynomial" (coefficients `poly_coeffs` of
        w/L in powers of X/L, default `DEFAULT_POLY_COEFFS`) or a callable w(X) [m] -> [m].
    edge_length: target element edge h in metres (2 mm: ~ the fluid grid's 2.5 mm cells); the
        Triangle area bound is sqrt(3)/4 h^2, outline segments are <= h, shorter on the head and
        the thin tail.
    min_angle: Triangle's minimum angle in degrees (30: well-conditioned elements, far from the
        33.8 degree limit where Triangle may not terminate).
    n_outline: about this many outline points instead of the automatic spacing.
    actuator_spacing: distance in metres between actuated stations along X (4 mm: about every
        other surface element at the default h).
    actuator_x_range: (start, end) of the actuated stations as fractions of L; the default
        (0.05, 0.95) is the body between the tail taper (s > s_t = 0.95 L) and the round head
        (s < s_b = 0.04 L) of the Kern profile.
    tail_tip_width: full width in metres of the blunt tail tip, default w_t = 0.01 L (the profile
        is clamped to half of it near X = 0, see `outline_half_width`); 0 keeps a pointed tail.
    elements_across: grade the mesh so that the body behind its widest point is at least this
        many elements across (`graded_edge`): linear triangles are too stiff in bending with few
        across. 2 (or less) grades only the outline: the paper's uniform mesh.
    Raises ConfigError for impossible arguments, MeshError for an unusable profile.
    """
    _check_arguments(length, edge_length, min_angle, actuator_spacing, actuator_x_range)
    w = make_profile(profile, length, poly_coeffs)
    check_profile(w, length)
    tip = 0.01 * length if tail_tip_width is None else float(tail_tip_width)
    w_out = outline_half_width(w, length, tip)
    xy = sample_outline(w_out, length, edge_length, n_outline, elements_across)
    check_outline(xy)
    size = graded_edge(w_out, length, edge_length, elements_across) if elements_across > 2 else None
    points, triangles = triangulate_outline(xy, edge_length, min_angle, size)
    surface = surface_polyline(points, triangles)
    actuator = actuator_groups(points, triangles, length, actuator_spacing, actuator_x_range)
    mesh = FishMesh(points=points, triangles=triangles, surface=surface, actuator=actuator,
                    length=float(length))
    check_mesh(mesh)
    return mesh


def _check_arguments(length, edge_length, min_angle, spacing, x_range) -> None:
    """ConfigError with a one-line fix for arguments `make_fish_mesh` cannot use."""
    if not (np.isfinite(length) and length > 0.0):
        raise ConfigError(f"fish length must be > 0 metres, got {length}")
    if not (np.isfinite(edge_length) and 0.0 < edge_length <= 0.25 * length):
        raise ConfigError(f"edge_length must be in (0, L/4] metres, got {edge_length} (try 2e-3)")
    if not 0.0 < min_angle <= MAX_MIN_ANGLE:
        raise ConfigError(f"min_angle must be in (0, {MAX_MIN_ANGLE}] degrees, got {min_angle}: "
                          "Triangle may not terminate above that (try 30)")
    if not (np.isfinite(spacing) and spacing > 0.0):
        raise ConfigError(f"actuator_spacing must be > 0 metres, got {spacing} (try 4e-3)")
    if not (len(x_range) == 2 and 0.0 <= x_range[0] < x_range[1] <= 1.0):
        raise ConfigError(f"actuator_x_range must be (start, end) fractions of L with 0 <= start < end <= 1, "
                          f"got {x_range}")


# ---------------------------------------------------------------- quality and checks


def mesh_quality(mesh: FishMesh) -> dict:
    """Quality numbers of a mesh: angles in degrees, areas in m^2, edge lengths in m, counts."""
    angles = element_angles(mesh.points, mesh.triangles)
    areas = element_areas(mesh.points, mesh.triangles)
    e = np.unique(np.sort(edge_list(mesh.triangles), axis=1), axis=0)
    lengths = np.linalg.norm(mesh.points[e[:, 1]] - mesh.points[e[:, 0]], axis=1)
    return {
        "n_nodes": mesh.n_nodes, "n_elements": mesh.n_elements, "n_surface": len(mesh.surface),
        "n_top": int(np.sum(mesh.actuator == ACTUATOR_TOP)),
        "n_bottom": int(np.sum(mesh.actuator == ACTUATOR_BOTTOM)),
        "min_angle": float(angles.min()), "max_angle": float(angles.max()),
        "min_area": float(areas.min()), "max_area": float(areas.max()), "area": float(areas.sum()),
        "edge_min": float(lengths.min()), "edge_mean": float(lengths.mean()),
        "edge_max": float(lengths.max()),
    }


def check_mesh(mesh: FishMesh, degenerate_tol: float = 1e-8) -> None:
    """Raise MeshError unless the mesh can be simulated: shapes and dtypes of the contract,
    every element ccw with area > degenerate_tol * median area, and `surface` the closed ccw
    loop of all boundary edges."""
    _check_arrays(mesh)
    areas = element_areas(mesh.points, mesh.triangles)
    if np.any(areas < 0.0):
        t = int(np.flatnonzero(areas < 0.0)[0])
        raise MeshError(f"element {t} is inverted (area {areas[t]:.3g} m^2 < 0; triangles must be "
                        "counter-clockwise); re-mesh with `fishsim mesh`")
    tiny = degenerate_tol * float(np.median(areas))
    if np.any(areas <= tiny):
        t = int(np.flatnonzero(areas <= tiny)[0])
        raise MeshError(f"element {t} is degenerate (area {areas[t]:.3g} m^2 ~ 0); "
                        "re-mesh with `fishsim mesh`")
    _check_surface(mesh)


def _check_arrays(mesh: FishMesh) -> None:
    """MeshError if the arrays break the FishMesh contract (shapes, dtypes, index range)."""
    p, t, s, a = mesh.points, mesh.triangles, mesh.surface, mesh.actuator
    if p.ndim != 2 or p.shape[1] != 2 or p.dtype != np.float64 or not np.all(np.isfinite(p)):
        raise MeshError(f"mesh points must be finite float64 [N, 2], got {p.dtype} {p.shape}")
    if t.ndim != 2 or t.shape[1] != 3 or t.dtype != np.int64 or len(t) == 0:
        raise MeshError(f"mesh triangles must be int64 [T, 3] with T > 0, got {t.dtype} {t.shape}")
    if t.min() < 0 or t.max() >= len(p) or s.dtype != np.int64 or s.ndim != 1 or len(s) < 3:
        raise MeshError("mesh triangles or surface refer to missing nodes (or surface has < 3 nodes)")
    if s.min() < 0 or s.max() >= len(p) or len(np.unique(s)) != len(s):
        raise MeshError("mesh surface must list existing nodes, each once")
    if a.shape != (len(t),) or a.dtype != np.int8 or not np.all(np.isin(a, (0, 1, 2))):
        raise MeshError(f"mesh actuator must be int8 [T] with values 0, 1, 2, got {a.dtype} {a.shape}")
    if not (np.isfinite(mesh.length) and mesh.length > 0.0):
        raise MeshError(f"mesh length must be > 0 metres, got {mesh.length}")


def _check_surface(mesh: FishMesh) -> None:
    """MeshError unless `surface` is closed, ccw and made of exactly the boundary edges."""
    boundary = edge_list(mesh.triangles)[boundary_edges(mesh.triangles)]
    loop = np.stack([mesh.surface, np.roll(mesh.surface, -1)], axis=1)
    if _edge_set(loop) != _edge_set(boundary):
        raise MeshError(f"mesh surface polyline ({len(loop)} edges) is not the closed ccw loop of the "
                        f"{len(boundary)} boundary edges; re-mesh with `fishsim mesh`")
    if polygon_signed_area(mesh.points[mesh.surface]) <= 0.0:
        raise MeshError("mesh surface polyline is not counter-clockwise; re-mesh with `fishsim mesh`")


def _edge_set(edges: np.ndarray) -> set:
    """Directed edges [E, 2] as a set of (a, b) tuples."""
    return set(map(tuple, edges.tolist()))
