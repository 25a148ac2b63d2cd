"""The banded Cholesky of the solid's SPD matrices solves to round-off, and an indefinite matrix
falls back to SuperLU."""

import numpy as np
import scipy.sparse as sp

from fishsim.mesh import make_fish_mesh
from fishsim.solid import SolidModel
from fishsim.solid.banded import BandedCholesky, spd_factor
from fishsim.solid.preconditioner import pd_matrix, rest_newton_matrix


def test_banded_cholesky_solves_the_fish_matrices():
    model = SolidModel(make_fish_mesh(edge_length=4e-3))
    rng = np.random.default_rng(0)
    for K in (rest_newton_matrix(model, 6e5), pd_matrix(model, 6e5)):
        solver = spd_factor(K)
        assert isinstance(solver, BandedCholesky)
        b = rng.standard_normal((K.shape[0], 3))
        x = solver.solve(b)
        assert np.abs(K @ x - b).max() < 1e-10 * np.abs(b).max()
        np.testing.assert_allclose(solver.solve(b[:, 0]), x[:, 0], rtol=1e-12, atol=0)


def test_indefinite_matrix_falls_back_to_lu():
    K = sp.diags([2.0, -1.0, 3.0]).tocsc()
    solver = spd_factor(K)
    assert not isinstance(solver, BandedCholesky)
    np.testing.assert_allclose(solver.solve(np.array([2.0, 1.0, 3.0])), [1.0, -1.0, 1.0])
