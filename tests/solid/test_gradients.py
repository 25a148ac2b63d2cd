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


def _central_difference(loss, args, i, eps, g):
    """(random unit direction d for args[i], central difference of loss along d with step eps)."""
    d = torch.randn(args[i].shape, generator=g)
    d = d / d.norm()
    plus = [a + eps * d if j == i else a for j, a in enumerate(args)]
    minus = [a - eps * d if j == i else a for j, a in enumerate(args)]
    with torch.no_grad():
        return d, (loss(*plus) - loss(*minus)) / (2 * eps)


def _check(model, tol=1e-4):
    args, weights, g = _problem(model)
    leaves = [a.clone().requires_grad_() for a in args]
    _loss(model, weights, *leaves).backward()
    for i, name in enumerate(EPS):
        d, fd = _central_difference(lambda *x: _loss(model, weights, *x), args, i, EPS[name], g)
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


def _layer_loss(mesh, elements, weights, thickness, C, omega, gamma, E, differentiable: bool):
    """Tail-and-body loss after STEPS steps of the layer-muscled fish driven by the wave
    controller from t = 0.3 s (the ramp mostly done)."""
    from fishsim.solid.controller import WaveController
    from fishsim.solid.muscles import layer_muscles, layer_weights

    model = SolidModel(mesh, options=PDOptions(**TIGHT),
                       muscles=layer_muscles(mesh, float(thickness.detach()), elements=elements))
    w, share = layer_weights(model, thickness) if differentiable else (None, None)
    ctrl = WaveController(C, omega, gamma)
    q, qdot = rest_state(model, len(C))
    for k in range(STEPS):
        u = ctrl.contraction(model, 0.3 + k * model.h, top_share=share)
        q, qdot = pd_step(model, q, qdot, u, None, E, muscle_weight=w)
    return (weights[0] * q).sum() + 0.01 * (weights[1] * qdot).sum()


def test_layer_gradients_wrt_controller_E_and_thickness_match_finite_differences(tiny_mesh):
    """d loss / d(C, omega, gamma, E, layer thickness) through the muscle layer: the adjoint (with
    the thickness reaching the muscles' weights and top shares) against central differences.
    The muscle list is the layer's at a larger thickness, so that both sides of the difference
    share it (elements outside the layer at the nominal thickness have weight 0)."""
    from fishsim.solid.muscles import layer_muscles

    g = torch.Generator().manual_seed(3)
    elements = layer_muscles(tiny_mesh, 0.45).elements
    weights = (torch.randn((2, tiny_mesh.n_nodes, 2), generator=g), torch.randn((2, tiny_mesh.n_nodes, 2), generator=g))
    args = [torch.tensor(0.3), torch.tensor([12.6, 15.0]), torch.tensor([31.4, 25.0]), torch.tensor([31.4, 28.0]),
            torch.tensor([6e5, 4e5])]
    leaves = [a.clone().requires_grad_() for a in args]
    _layer_loss(tiny_mesh, elements, weights, *leaves, differentiable=True).backward()
    eps = {"thickness": 1e-5, "C": 1e-4, "omega": 1e-4, "gamma": 1e-4, "E": 1.0}
    def loss(*x):
        return _layer_loss(tiny_mesh, elements, weights, *x, differentiable=False)

    for i, name in enumerate(eps):
        d, fd = _central_difference(loss, args, i, eps[name], g)
        adjoint = (leaves[i].grad * d).sum()
        assert abs(fd.item()) > 1e-8, name                       # the parameter does act
        assert adjoint.item() == pytest.approx(fd.item(), rel=1e-4), name


def _episode_loss(mesh, elements, thickness, C, segment: int, differentiable: bool, frames: int = 21):
    """Final tail y + head x (summed over a batch of 2) after `frames` frames in vacuum of the
    layer-muscled fish, through `rollout` (the thickness as SwimParams.muscle_thickness)."""
    from fishsim.coupling import CouplingConfig
    from fishsim.fields import Grid
    from fishsim.fluid.vacuum import Vacuum
    from fishsim.rollout import Swimmer, SwimParams, rollout
    from fishsim.solid.controller import WaveController
    from fishsim.solid.muscles import layer_muscles

    model = SolidModel(mesh, options=PDOptions(**TIGHT),
                       muscles=layer_muscles(mesh, float(thickness.detach()), elements=elements))
    swimmer = Swimmer(model, Vacuum(Grid()), CouplingConfig())
    ctrl = WaveController.default(mesh.length, batch=2)
    params = SwimParams(WaveController(C, ctrl.omega, ctrl.gamma), torch.tensor([6e5, 4e5], dtype=torch.float64),
                        muscle_thickness=thickness if differentiable else None)
    _, m = rollout(swimmer, swimmer.initial_state(params, (0.0, 0.0)), params, frames, segment=segment)
    return (m["tail_y"][-1] + m["head_x"][-1]).sum()


@pytest.mark.parametrize("segment", [0, 7])
def test_rollout_gradient_wrt_layer_thickness_matches_finite_differences(tiny_mesh, segment):
    """d(final tail y + head x) / d(layer thickness, C) through a 21-frame vacuum episode of
    `rollout`, plain (segment 0) and checkpointed (segments of 7 frames, recomputed in the
    backward), against central differences; the thickness reaches the PD weights and the top
    shares of the muscles (SwimParams.muscle_thickness)."""
    from fishsim.solid.muscles import layer_muscles

    g = torch.Generator().manual_seed(5)
    elements = layer_muscles(tiny_mesh, 0.45).elements
    args = [torch.tensor(0.3, dtype=torch.float64), torch.tensor([12.6, 15.0], dtype=torch.float64)]
    leaves = [a.clone().requires_grad_() for a in args]
    _episode_loss(tiny_mesh, elements, *leaves, segment=segment, differentiable=True).backward()

    def loss(*x):
        return _episode_loss(tiny_mesh, elements, *x, segment=0, differentiable=False)

    for i, (name, eps) in enumerate({"thickness": 1e-3, "C": 1e-3}.items()):
        d, fd = _central_difference(loss, args, i, eps, g)
        adjoint = (leaves[i].grad * d).sum()
        assert abs(fd.item()) > 1e-6, name                       # the parameter does act
        assert adjoint.item() == pytest.approx(fd.item(), rel=1e-4), (name, adjoint.item(), fd.item())
