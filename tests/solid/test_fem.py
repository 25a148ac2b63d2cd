"""FEM quantities: rest shapes, F = G q, lumped masses."""

import numpy as np

from fishsim.solid.fem import fem_quantities


def test_masses_are_lumped_from_each_triangles_own_area(tiny_mesh):
    fem = fem_quantities(tiny_mesh, density=100.0)
    expected = np.zeros(tiny_mesh.n_nodes)
    for tri, area in zip(tiny_mesh.triangles, fem.area):
        expected[tri] += 100.0 * area / 3
    np.testing.assert_allclose(fem.mass, expected, rtol=1e-14)
    np.testing.assert_allclose(fem.mass.sum(), 100.0 * fem.area.sum(), rtol=1e-14)


def test_deformation_gradient_of_an_affine_map_is_its_matrix(tiny_mesh):
    fem = fem_quantities(tiny_mesh, density=100.0)
    A = np.array([[1.2, -0.3], [0.5, 0.9]])
    x = tiny_mesh.points @ A.T + np.array([0.1, -2.0])
    T = fem.n_elements
    for a in range(2):
        Fa = (fem.G @ x[:, a]).reshape(2, T)            # rows j
        np.testing.assert_allclose(Fa, np.broadcast_to(A[a][:, None], (2, T)), atol=1e-12)


def test_element_operator_matches_sparse_operator(tiny_mesh):
    fem = fem_quantities(tiny_mesh, density=100.0)
    x = np.random.default_rng(0).standard_normal((tiny_mesh.n_nodes, 2))
    xe = x[tiny_mesh.triangles].reshape(-1, 6)           # DOF 2k + a
    vecF = np.einsum("eij,ej->ei", fem.element_G, xe)     # index 2a + j
    for a in range(2):
        for j in range(2):
            np.testing.assert_allclose(vecF[:, 2 * a + j], (fem.G @ x[:, a]).reshape(2, -1)[j], atol=1e-12)
