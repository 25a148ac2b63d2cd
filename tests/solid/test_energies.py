"""Element projections (2D closed forms) and their differentials."""

import numpy as np
import pytest
from scipy.linalg import polar
from scipy.optimize import minimize_scalar

from fishsim.solid import energies as en

RNG = np.random.default_rng(1)
MATRICES = [np.eye(2) + 0.3 * RNG.standard_normal((2, 2)) for _ in range(8)]


def coords(F):
    return [np.array([[v]]) for v in en.conformal_parts(F[0, 0], F[0, 1], F[1, 0], F[1, 1])]


def matrix(c):
    F00, F01, F10, F11 = (float(np.squeeze(v)) for v in en.from_conformal(*c))
    return np.array([[F00, F01], [F10, F11]])


@pytest.mark.parametrize("F", MATRICES)
def test_corotated_projection_is_the_polar_rotation(F):
    a, b, *_ = coords(F)
    aR, bR, _ = en.corotated_projection(a, b)
    R = matrix((aR, bR, 0 * a, 0 * a))
    np.testing.assert_allclose(R, polar(F)[0], atol=1e-12)


@pytest.mark.parametrize("F", MATRICES)
def test_volume_projection_is_the_closest_det_one_matrix(F):
    *D, _ = en.volume_projection(*coords(F))
    D = matrix(D)
    U, s, Vt = np.linalg.svd(F)
    if np.linalg.det(U @ Vt) < 0:
        U[:, 1] *= -1
        s[1] *= -1
    best = minimize_scalar(lambda x: (s[0] - x) ** 2 + (s[1] - 1 / x) ** 2, bounds=(1e-3, 10), method="bounded",
                           options={"xatol": 1e-12}).x
    assert np.linalg.det(D) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(D, U @ np.diag([best, 1 / best]) @ Vt, atol=1e-7)


def _fd(proj, F, dF, eps=1e-6):
    return (proj(F + eps * dF) - proj(F - eps * dF)) / (2 * eps)


@pytest.mark.parametrize("F", MATRICES[:4])
def test_differentials_match_finite_differences(F):
    dF = RNG.standard_normal((2, 2))
    d = coords(dF)
    c = coords(F)
    aR, bR, cc = en.corotated_projection(c[0], c[1])
    dR = en.corotated_projection_differential(aR, bR, cc, d[0], d[1])
    rot = lambda M: matrix(en.corotated_projection(*coords(M)[:2])[:2] + (0 * c[0], 0 * c[0]))
    np.testing.assert_allclose(matrix(dR + (0 * c[0], 0 * c[0])), _fd(rot, F, dF), atol=1e-8)

    *_, t = en.volume_projection(*c)
    dD = en.volume_projection_differential(*c, t, *d)
    vol = lambda M: matrix(en.volume_projection(*coords(M))[:4])
    np.testing.assert_allclose(matrix(dD), _fd(vol, F, dF), atol=1e-8)

    a = 0.7
    _p0, _p1, n0, n1, length = en.muscle_projection(F[0, 0], F[1, 0], a)
    dp = en.muscle_projection_differential(n0, n1, length, a, dF[0, 0], dF[1, 0])
    mus = lambda M: np.array(en.muscle_projection(M[0, 0], M[1, 0], a)[:2])
    np.testing.assert_allclose(np.array(dp), _fd(mus, F, dF), atol=1e-8)
