"""Adjoint gradients of a multi-step rollout against central finite differences (float64)."""

import pytest
import torch

from fishsim.solid import PDOptions, SolidMaterial, SolidModel, pd_step, rest_state

STEPS = 3


def _problem(model, seed=0, B=2):
    g = torch.Generator().manual_seed(seed)
    q0, _ = rest_state(model, B)
    q0 = q0 + 1e-3 * torch.randn(q0.shape, generator=g)
    qdot0 = 0.05 * torch.randn(q0.shape, generator=g)
    u = 0.2 * torch.rand((STEPS, B, model.n_muscles), generator=g)
    mass = torch.as_tensor(model.fem.mass)[:, None]
    f = 5 * mass * torch.randn((STEPS, B, model.n_nodes, 2), generator=g)     # ~5 m/s^2
    E = torch.tensor([6e5, 4e5])[:B]
    weights = (torch.randn(q0.shape, generator=g), torch.randn(q0.shape, generator=g))
    return [q0, qdot0, u, f, E], weights, g


def _loss(model, weights, q0, qdot0, u, f, E):
    q, qdot = q0, qdot0
    for k in range(STEPS):
        q, qdot = pd_step(model, q, qdot, u[k], f[k], E)
    return (weights[0] * q).sum() + 0.01 * (weights[1] * qdot).sum()


# finite-difference step and direction scale per argument (q0 m, qdot0 m/s, u 1, f N, E Pa)
EPS = {"q0": 1e-6, "qdot0": 1e-4, "u": 1e-4, "f": 1e-4, "E": 1.0}


def _check(model, tol=1e-4):
    args, weights, g = _problem(model)
    leaves = [a.clone().requires_grad_() for a in args]
    _loss(model, weights, *leaves).backward()
    for i, name in enumerate(EPS):
        d = torch.randn(args[i].shape, generator=g)
        d = d / d.norm()
        plus = [a + EPS[name] * d if j == i else a for j, a in enumerate(args)]
        minus = [a - EPS[name] * d if j == i else a for j, a in enumerate(args)]
        with torch.no_grad():
            fd = (_loss(model, weights, *plus) - _loss(model, weights, *minus)) / (2 * EPS[name])
        adjoint = (leaves[i].grad * d).sum()
        assert adjoint.item() == pytest.approx(fd.item(), rel=tol), name


TIGHT = {"atol": 1e-9, "backward_rtol": 1e-12, "backward_max_iter": 500}


@pytest.mark.parametrize("method", ["auto", "direct"])
def test_rollout_gradients_match_finite_differences(tiny_mesh, method):
    _check(SolidModel(tiny_mesh, options=PDOptions(backward_method=method, **TIGHT)))


def test_rollout_gradients_with_volume_term(tiny_mesh):
    _check(SolidModel(tiny_mesh, SolidMaterial(volume_term=True), options=PDOptions(**TIGHT)))


@pytest.mark.parametrize("preconditioner", ["rest_newton", "pd"])
def test_forward_preconditioners_agree(tiny_mesh, preconditioner):
    args, _, _ = _problem(SolidModel(tiny_mesh))
    ref = SolidModel(tiny_mesh, options=PDOptions(**TIGHT))
    other = SolidModel(tiny_mesh, options=PDOptions(preconditioner=preconditioner, **TIGHT))
    q0, qdot0, u, f, E = args
    a = pd_step(ref, q0, qdot0, u[0], f[0], E)[0]
    b = pd_step(other, q0, qdot0, u[0], f[0], E)[0]
    torch.testing.assert_close(a, b, atol=1e-10, rtol=0)
