"""Fish profile and triangulation (fishsim.mesh): docs/physics.md section 2, paper Fig. 9."""

import itertools

import numpy as np
import pytest
from scipy.integrate import quad

from fishsim.errors import ConfigError, MeshError
from fishsim.mesh import (
    ACTUATOR_BOTTOM,
    ACTUATOR_TOP,
    DEFAULT_POLY_COEFFS,
    FishMesh,
    boundary_edges,
    check_mesh,
    check_outline,
    element_angles,
    element_areas,
    kern_profile,
    make_fish_mesh,
    mesh_quality,
    polynomial_profile,
    surface_elements,
)
from fishsim.mesh.triangulate import edge_list, graded_edge, outline_half_width

L = 0.2
W_H, S_B, S_T, W_T = 0.04 * L, 0.04 * L, 0.95 * L, 0.01 * L


@pytest.fixture(scope="module")
def mesh() -> FishMesh:
    return make_fish_mesh()


def _area_integral(w, length=L) -> float:
    """int_0^L 2 w(X) dX, m^2, split at the profile's kinks."""
    breaks = [0.0, L - S_T, L - S_B, length]
    return sum(quad(lambda x: 2.0 * w(np.array([x]))[0], a, b, limit=200)[0] for a, b in itertools.pairwise(breaks))


# ---------------------------------------------------------------- profile


def test_kern_profile_known_points():
    w = kern_profile(L)
    def s(x):  # X from s = L - X (and back)
        return L - x

    X = np.linspace(0.0, L, 200001)
    assert w(X).max() == pytest.approx(W_H, rel=1e-12)
    assert w(np.array([s(S_B)]))[0] == pytest.approx(W_H, rel=1e-12)  # widest at s = s_b
    assert w(np.array([s(S_T)]))[0] == pytest.approx(W_T, rel=1e-12)
    assert w(np.array([0.0, L])) == pytest.approx([0.0, 0.0], abs=1e-15)  # tail and nose tips
    assert w(np.array([s(0.975 * L)]))[0] == pytest.approx(0.5 * W_T, rel=1e-12)  # linear taper
    eps = 1e-9
    for s_k in (S_B, S_T):  # continuous across the joins
        left, right = w(np.array([s(s_k - eps), s(s_k + eps)]))
        assert left == pytest.approx(right, abs=1e-8)


def test_polynomial_profile_defaults():
    w = polynomial_profile(L)
    X = np.linspace(0.0, L, 2001)
    assert w(np.array([0.0]))[0] == pytest.approx(DEFAULT_POLY_COEFFS[0] * L)
    assert w(np.array([L]))[0] == pytest.approx(0.0, abs=1e-15)
    assert np.all(w(X[1:-1]) > 0.0)
    assert 0.8 < X[np.argmax(w(X))] / L < 0.82


def test_negative_width_polynomial_raises():
    with pytest.raises(MeshError, match="non-positive half-width"):
        make_fish_mesh(profile="polynomial", poly_coeffs=[0.02, -0.1, 0.05])


def test_non_finite_profile_raises():
    with pytest.raises(MeshError, match="not finite"):
        make_fish_mesh(profile=lambda X: np.where(X > 0.1, np.nan, 0.01))


def test_self_intersecting_outline_raises():
    bow_tie = np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0], [0.0, 1.0]])
    with pytest.raises(MeshError, match="self-intersects"):
        check_outline(bow_tie)
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    check_outline(square)
    with pytest.raises(MeshError, match="counter-clockwise"):
        check_outline(square[::-1])


def test_bad_arguments_raise_config_error():
    with pytest.raises(ConfigError, match="min_angle"):
        make_fish_mesh(min_angle=40.0)
    with pytest.raises(ConfigError, match="unknown fish profile"):
        make_fish_mesh(profile="shark")


# ---------------------------------------------------------------- triangulation


def test_area_matches_profile_integral(mesh):
    """Mesh area = int 2 w_out dX to 5e-4: the outline's chords cut R^2 theta^3 / 12 each off
    the round head (R = w_h = 8 mm, theta = pi/16 per segment, 16 segments: 6.4e-7 m^2 = 3e-4).
    And = int 2 w dX of the exact Kern profile to 0.5% (the blunt tail tip adds
    w_t/2 * 0.025 L ~ 0.2%)."""
    area = element_areas(mesh.points, mesh.triangles).sum()
    w_out = outline_half_width(kern_profile(L), L, W_T)
    assert area == pytest.approx(_area_integral(w_out), rel=5e-4)
    assert area == pytest.approx(_area_integral(kern_profile(L)), rel=5e-3)


def test_triangles_ccw_and_angle_bound(mesh):
    assert mesh.points.dtype == np.float64 and mesh.triangles.dtype == np.int64
    assert np.all(element_areas(mesh.points, mesh.triangles) > 0.0)
    assert element_angles(mesh.points, mesh.triangles).min() >= 30.0 - 1e-6
    assert mesh.points[:, 0].min() == 0.0 and mesh.points[:, 0].max() == pytest.approx(L, abs=1e-15)


def test_min_angle_is_honoured():
    coarse = make_fish_mesh(edge_length=5e-3, min_angle=33.0)
    assert mesh_quality(coarse)["min_angle"] >= 33.0 - 1e-6


def test_edge_length_near_target(mesh):
    q = mesh_quality(mesh)
    assert 1e-3 < q["edge_mean"] < 2e-3
    assert q["max_area"] <= np.sqrt(3.0) / 4.0 * 2e-3**2 * (1 + 1e-9)


def test_graded_mesh_spans_the_rear_body_with_enough_elements():
    """Behind the widest point each element is no larger than the graded target sqrt(3)/4 h(X)^2,
    h = clip(2 w(X) / n, h0 / 4, h0), so a cut across the body at X meets about n elements or more;
    the uniform mesh (n = 2) has far fewer across its thin rear body."""
    w_out = outline_half_width(kern_profile(L), L, W_T)
    counts = {}
    for n in (2, 6):
        m = make_fish_mesh(elements_across=n)
        xc = m.points[m.triangles, 0].mean(axis=1)
        area = element_areas(m.points, m.triangles)
        h = graded_edge(w_out, L, 2e-3, n)(xc)
        assert np.all(area <= np.sqrt(3.0) / 4.0 * h**2 * (1 + 1e-9)) or n == 2
        cut = 0.1 * L  # elements crossed by the line X = L/10 (full width 2 w = 5.3 mm); a row of
        # triangles across the body is crossed about twice
        x = m.points[m.triangles, 0]
        counts[n] = int(np.sum((x.min(axis=1) < cut) & (x.max(axis=1) > cut)))
    assert counts[6] >= 2 * 6 and counts[6] > 2 * counts[2]


def test_surface_is_the_closed_ccw_boundary(mesh):
    s = mesh.surface
    x, y = mesh.points[s, 0], mesh.points[s, 1]
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0.0  # ccw
    loop = set(zip(s.tolist(), np.roll(s, -1).tolist()))  # closed: last -> first included
    boundary = set(map(tuple, edge_list(mesh.triangles)[boundary_edges(mesh.triangles)].tolist()))
    assert loop == boundary
    assert len(np.unique(s)) == len(s)
    assert tuple(mesh.points[s[0]]) == (L, 0.0)  # starts at the nose


def test_actuator_groups(mesh):
    top = np.flatnonzero(mesh.actuator == ACTUATOR_TOP)
    bottom = np.flatnonzero(mesh.actuator == ACTUATOR_BOTTOM)
    assert len(top) > 20 and len(bottom) > 20
    assert np.all(mesh.points[mesh.triangles[top], 1] > 0.0)
    assert np.all(mesh.points[mesh.triangles[bottom], 1] < 0.0)
    assert np.all(np.isin(mesh.actuated, surface_elements(mesh.triangles)))
    assert abs(len(top) - len(bottom)) <= 0.1 * max(len(top), len(bottom))
    x_top = mesh.points[mesh.triangles[top], 0].mean(axis=1)
    x_bot = mesh.points[mesh.triangles[bottom], 0].mean(axis=1)
    assert x_top.min() >= 0.05 * L and x_top.max() <= 0.95 * L
    # roughly mirror-symmetric: each top muscle has a bottom one within half a spacing (2 mm)
    assert np.all(np.min(np.abs(x_top[:, None] - x_bot[None, :]), axis=1) <= 2e-3)
    # spaced: consecutive muscles of a side are about actuator_spacing = 4 mm apart
    assert np.median(np.diff(np.sort(x_top))) == pytest.approx(4e-3, rel=0.25)


def test_polynomial_and_custom_profiles_mesh():
    poly = make_fish_mesh(profile="polynomial", edge_length=4e-3)
    assert element_areas(poly.points, poly.triangles).sum() == pytest.approx(
        _area_integral(polynomial_profile(L)), rel=2e-3)
    a, b = L / 2, 0.02  # ellipse: w = b sqrt(1 - ((X - a)/a)^2), area pi a b
    ellipse = make_fish_mesh(profile=lambda X: b * np.sqrt(np.clip(1 - ((X - a) / a) ** 2, 0, None)),
                             edge_length=4e-3, tail_tip_width=0.0)
    assert element_areas(ellipse.points, ellipse.triangles).sum() == pytest.approx(np.pi * a * b, rel=2e-3)
    assert mesh_quality(ellipse)["min_angle"] >= 30.0 - 1e-6


# ---------------------------------------------------------------- check_mesh


def test_check_mesh_rejects_inverted_degenerate_and_bad_surface(mesh):
    tri = mesh.triangles.copy()
    tri[7] = tri[7, [0, 2, 1]]
    with pytest.raises(MeshError, match="element 7 is inverted"):
        check_mesh(FishMesh(mesh.points, tri, mesh.surface, mesh.actuator, mesh.length))
    pts = mesh.points.copy()
    a, b, c = mesh.triangles[100]
    pts[c] = 0.5 * (pts[a] + pts[b])  # collapse element 100 (its neighbours may invert first)
    with pytest.raises(MeshError, match="degenerate|inverted"):
        check_mesh(FishMesh(pts, mesh.triangles, mesh.surface, mesh.actuator, mesh.length))
    with pytest.raises(MeshError, match="surface polyline"):
        check_mesh(FishMesh(mesh.points, mesh.triangles, mesh.surface[::-1].copy(), mesh.actuator, mesh.length))
    with pytest.raises(MeshError, match="surface polyline"):
        check_mesh(FishMesh(mesh.points, mesh.triangles, mesh.surface[:-1].copy(), mesh.actuator, mesh.length))


def test_mesh_does_not_depend_on_the_outline_last_bits(monkeypatch):
    """The outline's last bits depend on the CPU (numpy's cos/arctan2: SIMD library or libm);
    Triangle's refinement turns a 1-2 ulp change of it into a different mesh (1761-1787 nodes
    for the default fish before the outline was snapped). Snapped, every such outline gives the
    same mesh, and the default fish has the same 1803 nodes on every machine."""
    import fishsim.mesh.triangulate as tri

    reference = make_fish_mesh()
    assert reference.points.shape == (1803, 2)
    exact = tri.triangulate_outline
    rng = np.random.default_rng(0)
    for _ in range(4):
        def jittered(xy, *args, **kwargs):
            return exact(xy * (1.0 + rng.integers(-2, 3, xy.shape) * np.finfo(float).eps), *args, **kwargs)

        monkeypatch.setattr(tri, "triangulate_outline", jittered)
        again = make_fish_mesh()
        np.testing.assert_array_equal(again.points, reference.points)
        np.testing.assert_array_equal(again.triangles, reference.triangles)
