"""Discrete identities and second-order convergence of the MAC stencils (fishsim.fluid.grid)."""

import math

import pytest
import torch

from fishsim.fields import Boundary, Grid
from fishsim.fluid import grid as G

D = torch.float64


@pytest.fixture(autouse=True)
def _float64_default():
    """Stencil checks run in float64; restore the default so other tests in this worker keep theirs."""
    before = torch.get_default_dtype()
    torch.set_default_dtype(D)
    yield
    torch.set_default_dtype(before)


def _vertices(n, L=1.0):
    dx = L / n
    y, x = torch.meshgrid(torch.arange(n + 1, dtype=D) * dx, torch.arange(n + 1, dtype=D) * dx, indexing="ij")
    return x[None, None], y[None, None], dx


def _faces(n, L=1.0):
    """Coordinates of the vx faces, vy faces and centres of an n x n grid on [0, L]^2."""
    dx = L / n
    i, j = torch.arange(n, dtype=D), torch.arange(n + 1, dtype=D)
    yx, xx = torch.meshgrid((i + 0.5) * dx, j * dx, indexing="ij")
    yy, xy = torch.meshgrid(j * dx, (i + 0.5) * dx, indexing="ij")
    yc, xc = torch.meshgrid((i + 0.5) * dx, (i + 0.5) * dx, indexing="ij")
    e = lambda t: t[None, None]
    return (e(xx), e(yx)), (e(xy), e(yy)), (e(xc), e(yc)), dx


# A smooth, non-trivial test flow: stream function psi = exp(x) + exp(2y) + sin(x y) / 2.
def psi(x, y):
    return torch.exp(x) + torch.exp(2 * y) + 0.5 * torch.sin(x * y)


def u(x, y):  # d psi / dy
    return 2 * torch.exp(2 * y) + 0.5 * x * torch.cos(x * y)


def v(x, y):  # -d psi / dx
    return -torch.exp(x) - 0.5 * y * torch.cos(x * y)


def _interior(t):
    """A fixed physical sub-box [1/8, 7/8]^2 (approximately), away from the wall ghosts."""
    k = t.shape[-2] // 8
    return t[..., k:-k, k:-k]


def _order(errors):
    return [math.log2(errors[i] / errors[i + 1]) for i in range(len(errors) - 1)]


def test_div_curl_is_zero_to_round_off():
    a = torch.randn(3, 1, 21, 33)
    vel = G.curl(a, 0.01)
    assert vel[0].shape == (3, 1, 20, 33) and vel[1].shape == (3, 1, 21, 32)
    assert G.divergence(vel, 0.01).abs().max() < 1e-10 * vel[0].abs().max() / 0.01


def test_gradient_is_minus_adjoint_of_divergence():
    p = torch.randn(2, 1, 17, 23)
    vel = G.zero_walls((torch.randn(2, 1, 17, 24), torch.randn(2, 1, 18, 23)))
    dx = 0.37
    gx, gy = G.gradient(p, dx)
    lhs = (gx * vel[0]).sum() + (gy * vel[1]).sum()
    rhs = -(p * G.divergence(vel, dx)).sum()
    assert abs(lhs - rhs) < 1e-12 * abs(lhs)


def test_stream_function_inverts_curl():
    a = torch.randn(2, 1, 11, 19)
    vel = G.curl(a, 0.1)
    a2 = G.stream_function(vel, 0.1)
    torch.testing.assert_close(a2, a - a.mean(dim=(-2, -1), keepdim=True), rtol=0, atol=1e-12)
    _, p3 = G.potential_pressure(vel, torch.ones(2, 1, 10, 18), 0.1)
    assert p3.abs().max() < 1e-14


def test_laplacian_centres_is_div_grad_and_symmetric():
    p, q = torch.randn(1, 1, 9, 13), torch.randn(1, 1, 9, 13)
    Lp, Lq = G.laplacian_centres(p, 0.5), G.laplacian_centres(q, 0.5)
    assert abs((Lp * q).sum() - (p * Lq).sum()) < 1e-12
    assert abs(Lp.sum()) < 1e-12  # Neumann: no net source


def _errors(op, ns=(16, 32, 64)):
    return [op(n) for n in ns]


def test_curl_second_order():
    def err(n):
        x, y, dx = _vertices(n)
        vx, vy = G.curl(psi(x, y), dx)
        (xx, yx), (xy, yy), _, _ = _faces(n)
        return max((vx - u(xx, yx)).abs().max(), (vy - v(xy, yy)).abs().max())

    assert min(_order(_errors(err))) > 1.9


def test_divergence_and_gradient_second_order():
    def err(n):
        (xx, yx), (xy, yy), (xc, yc), dx = _faces(n)
        f = lambda x, y: torch.sin(2 * x) * torch.exp(y)
        div = G.divergence((f(xx, yx), f(xy, yy)), dx)
        e1 = (div - (2 * torch.cos(2 * xc) * torch.exp(yc) + f(xc, yc))).abs().max()
        gx, gy = G.gradient(f(xc, yc), dx)
        e2 = (gx - 2 * torch.cos(2 * xx) * torch.exp(yx))[..., 1:-1].abs().max()
        e3 = (gy - f(xy, yy))[..., 1:-1, :].abs().max()
        return max(e1, e2, e3)

    assert min(_order(_errors(err))) > 1.9


def test_laplacians_second_order():
    def err(n):
        (xx, yx), (xy, yy), (xc, yc), dx = _faces(n)
        lx, ly = G.laplacian_faces((u(xx, yx), v(xy, yy)), dx)
        # lap u = 8 e^{2y} - (x^2 + y^2) u_sin part; use finite-difference-free exact forms
        lap_u = 8 * torch.exp(2 * yx) - 0.5 * (xx**2 + yx**2) * xx * torch.cos(xx * yx) - yx * torch.sin(xx * yx)
        lap_v = -torch.exp(xy) + 0.5 * (xy**2 + yy**2) * yy * torch.cos(xy * yy) + xy * torch.sin(xy * yy)
        pc = psi(xc, yc)
        lap_p = G.laplacian_centres(pc, dx)
        lap_psi = torch.exp(xc) + 4 * torch.exp(2 * yc) - 0.5 * (xc**2 + yc**2) * torch.sin(xc * yc)
        return max(
            _interior(lx - lap_u).abs().max(), _interior(ly - lap_v).abs().max(), _interior(lap_p - lap_psi).abs().max()
        )

    assert min(_order(_errors(err))) > 1.9


def test_laplacian_eigenvalue_of_taylor_green_mode_with_slip_walls():
    n, k = 16, 1.0
    (xx, yx), (xy, yy), _, dx = _faces(n, math.pi / k)
    vel = (torch.sin(k * xx) * torch.cos(k * yx), -torch.cos(k * xy) * torch.sin(k * yy))
    lx, ly = G.laplacian_faces(vel, dx, G.FREE_SLIP)
    lam = -(8 / dx**2) * math.sin(k * dx / 2) ** 2
    torch.testing.assert_close(lx[..., 1:-1], lam * vel[0][..., 1:-1], rtol=0, atol=1e-12)
    torch.testing.assert_close(ly[..., 1:-1, :], lam * vel[1][..., 1:-1, :], rtol=0, atol=1e-12)


@pytest.mark.parametrize("scheme", ["central", "koren"])
def test_advection_second_order(scheme):
    def err(n):
        x, y, dx = _vertices(n)
        vel = G.curl(psi(x, y), dx)
        ax, ay = G.advection(vel, dx, G.NO_SLIP, scheme)
        (xx, yx), (xy, yy), _, _ = _faces(n)

        def dudx(x, y):
            return 0.5 * torch.cos(x * y) - 0.5 * x * y * torch.sin(x * y)

        ex = u(xx, yx) * dudx(xx, yx) + v(xx, yx) * (4 * torch.exp(2 * yx) - 0.5 * xx**2 * torch.sin(xx * yx))
        ey = u(xy, yy) * (-torch.exp(xy) + 0.5 * yy**2 * torch.sin(xy * yy)) + v(xy, yy) * (
            -0.5 * torch.cos(xy * yy) + 0.5 * xy * yy * torch.sin(xy * yy)
        )
        return max(_interior(ax - ex).abs().max(), _interior(ay - ey).abs().max())

    assert min(_order(_errors(err))) > 1.8


def test_interpolations_exact_for_linear_fields():
    (xx, yx), (xy, yy), (xc, yc), _ = _faces(8)
    lin = lambda x, y: 1 + 2 * x - 3 * y
    c = G.faces_to_centres((lin(xx, yx), lin(xy, yy)))
    torch.testing.assert_close(c, torch.cat([lin(xc, yc)] * 2, 1))
    fx, fy = G.centres_to_faces(lin(xc, yc))
    torch.testing.assert_close(fx[..., 1:-1], lin(xx, yx)[..., 1:-1])
    torch.testing.assert_close(fy[..., 1:-1, :], lin(xy, yy)[..., 1:-1, :])
    x, y, _ = _vertices(8)
    torch.testing.assert_close(G.vertices_to_centres(lin(x, y)), lin(xc, yc))
    torch.testing.assert_close(G.centres_to_vertices(lin(xc, yc))[..., 1:-1, 1:-1], lin(x, y)[..., 1:-1, 1:-1])


def test_vorticity_is_minus_laplacian_of_potential_inside():
    x, y, dx = _vertices(16)
    a = psi(x, y)
    w = G.vorticity(G.curl(a, dx), dx)
    lap_a = (a[..., 1:-1, 2:] + a[..., 1:-1, :-2] + a[..., 2:, 1:-1] + a[..., :-2, 1:-1] - 4 * a[..., 1:-1, 1:-1]) / dx**2
    torch.testing.assert_close(w[..., 1:-1, 1:-1], -lap_a)


def test_boundary_helpers():
    g = Grid(20, 40, 0.01)
    tank = G.closed_tank(g, 3, 5, batch=2)
    assert tank.mask.shape == (2, 1, 20, 40) and tank.mask[0, 0, 10, 20] == 0 and tank.mask[0, 0, 1, 20] == 1
    ch = G.channel(g, torch.tensor([0.1, 0.2]), 3, 5, batch=2)
    vx, _ = G.vector_to_faces(ch.velocity)
    bx, _ = G.face_masks(ch.mask)
    # the net flux through the left and right walls balances
    assert abs(vx[:, :, :, 0].sum() - vx[:, :, :, -1].sum()) < 1e-12
    assert ch.velocity[1, 0, 10, 0] == 0.2 and bx[0, 0, 10, 0] == 1
    both = G.union(tank, ch)
    torch.testing.assert_close(both.mask, tank.mask)


def test_stencils_are_differentiable_and_keep_dtype():
    a = torch.randn(1, 1, 6, 8, dtype=torch.float32, requires_grad=True)
    vel = G.curl(a, 0.1)
    ax, ay = G.advection(vel, 0.1)
    assert ax.dtype == torch.float32
    (ax.square().sum() + ay.square().sum()).backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


@pytest.mark.parametrize("dtype, tiny", [(torch.float64, 1e-310), (torch.float32, 1e-40)])
def test_union_gradient_is_finite_where_a_mask_is_subnormal(dtype, tiny):
    """A soft mask decays to subnormal values far from the body; there the mask-weighted mean
    v_d = (b1 v1 + b2 v2) / (b1 + b2) must keep a finite gradient (dividing by a subnormal w, the
    quotient's derivative -num / w^2 overflowed and the HydroNet Fig. 5 gradient came out NaN),
    and the union must still be the weighted mean wherever the masks are not negligible."""
    b1 = torch.tensor([tiny, 0.5, 0.0, 0.25], dtype=dtype).view(1, 1, 1, 4).requires_grad_()
    b2 = torch.tensor([0.0, 0.5, 0.0, 0.75], dtype=dtype).view(1, 1, 1, 4)
    v1, v2 = torch.ones(1, 2, 1, 4, dtype=dtype), -torch.ones(1, 2, 1, 4, dtype=dtype)
    u = G.union(Boundary(b1, v1), Boundary(b2, v2))
    (grad,) = torch.autograd.grad((u.mask * u.velocity).sum() + u.velocity.sum(), b1)
    assert torch.isfinite(grad).all()
    assert torch.allclose(u.velocity[0, 0, 0, 1:], torch.tensor([0.0, 0.0, -0.5], dtype=dtype))
    assert torch.allclose(u.mask[0, 0, 0], torch.tensor([tiny, 0.75, 0.0, 0.8125], dtype=dtype))
