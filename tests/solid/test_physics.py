"""Physics of the PD step: rest, conservation, dissipation, free oscillation, swimming wave."""

import math

import numpy as np
import pytest
import torch

from fishsim.solid import PDOptions, SolidModel, elastic, pd_step, rest_state
from fishsim.solid.controller import PAPER_C, WaveController

TIGHT = PDOptions(atol=1e-8, backward_rtol=1e-12)   # ~1e-10 of the nodal forces


@pytest.fixture(scope="module")
def model(coarse_mesh):
    return SolidModel(coarse_mesh, options=TIGHT)


def momentum(model, qdot):
    """Total linear momentum [B, 2] (kg m/s per unit depth)."""
    return (torch.as_tensor(model.fem.mass)[None, :, None] * qdot).sum(1)


def total_energy(model, q, qdot):
    """Kinetic + elastic energy [B] (J per unit depth), muscles relaxed."""
    kinetic = 0.5 * (torch.as_tensor(model.fem.mass)[None, :, None] * qdot**2).sum((1, 2)).numpy()
    X = elastic.to_columns(q.numpy())
    p = elastic.project(model, elastic.deformation_gradients(model, X), np.zeros((model.n_muscles, q.shape[0])),
                        np.full(q.shape[0], model.material.youngs_modulus))
    return kinetic + elastic.internal_energy(p)


def stretched(model, factor=1.05):
    """Rest shape stretched along the body about its centre, at rest."""
    q, qdot = rest_state(model)
    centre = q.mean(1, keepdim=True)
    return centre + (q - centre) * torch.tensor([factor, 1.0]), qdot


def test_rest_state_stays_at_rest(model):
    q0, qdot0 = rest_state(model, 2)
    q, qdot = q0, qdot0
    for _ in range(5):
        q, qdot = pd_step(model, q, qdot, torch.zeros(2, model.n_muscles))
    torch.testing.assert_close(q, q0, atol=1e-12, rtol=0)
    torch.testing.assert_close(qdot, qdot0, atol=1e-10, rtol=0)


def test_internal_actuation_conserves_linear_momentum(model):
    ctrl = WaveController.default(model.mesh.length, C=PAPER_C)
    q, qdot = rest_state(model)
    qdot = qdot + torch.tensor([0.03, -0.01])                        # drifting fish
    p0 = momentum(model, qdot)
    speeds = []
    for k in range(30):
        q, qdot = pd_step(model, q, qdot, ctrl.contraction(model, k * model.h))
        torch.testing.assert_close(momentum(model, qdot), p0, atol=1e-13, rtol=1e-11)
        speeds.append(qdot.norm(dim=2).max().item())
    assert max(speeds) > 0.1                                          # the body does move


def test_implicit_euler_does_not_gain_energy(model):
    q, qdot = stretched(model)
    energies = [total_energy(model, q, qdot)[0]]
    for _ in range(40):
        q, qdot = pd_step(model, q, qdot, torch.zeros(1, model.n_muscles))
        energies.append(total_energy(model, q, qdot)[0])
    energies = np.array(energies)
    assert np.all(np.diff(energies) <= 1e-9 * energies[0])
    assert energies[-1] < 0.5 * energies[0]                           # and it does dissipate


def test_stretched_free_body_oscillates_and_decays(model):
    q, qdot = stretched(model)
    nodes = model.mesh.points[:, 0]
    head, tail = int(np.argmax(nodes)), int(np.argmin(nodes))
    rest_length = nodes[head] - nodes[tail]
    strain = []
    for _ in range(60):
        q, qdot = pd_step(model, q, qdot, torch.zeros(1, model.n_muscles))
        strain.append(((q[0, head, 0] - q[0, tail, 0]).item() - rest_length) / rest_length)
    strain = np.array(strain)
    assert np.sum(np.diff(np.sign(strain)) != 0) >= 2                  # passes through rest length
    assert np.abs(strain[-20:]).max() < 0.5 * np.abs(strain[:20]).max()  # decays


def test_uniform_force_accelerates_centre_of_mass_at_F_over_M(model):
    B, steps = 2, 5
    q, qdot = rest_state(model, B)
    force = torch.tensor([[0.2, -0.1], [0.0, 0.5]])                   # N per node, per sample
    f_ext = force[:, None, :].expand(B, model.n_nodes, 2)
    M = model.fem.mass.sum()
    contraction = torch.full((B, model.n_muscles), 0.1)
    for _ in range(steps):
        q, qdot, info = pd_step(model, q, qdot, contraction, f_ext, return_info=True)
        assert info.converged.all(), info   # 0.5 N a node, 560 m/s^2: the Newton H0 alone stalled at 4e-5 N
    com_velocity = momentum(model, qdot) / M
    torch.testing.assert_close(com_velocity, steps * model.h * model.n_nodes * force / M, atol=1e-12, rtol=1e-10)


def test_batch_equals_per_sample(coarse_mesh):
    model = SolidModel(coarse_mesh, options=TIGHT)
    g = torch.Generator().manual_seed(3)
    B = 3
    q, qdot = rest_state(model, B)
    qdot = qdot + 0.02 * torch.randn(qdot.shape, generator=g)
    u = 0.2 * torch.rand((B, model.n_muscles), generator=g)
    f = 1e-3 * torch.randn(q.shape, generator=g)
    E = torch.tensor([6e5, 3e5, 6e5])
    batch = pd_step(model, q, qdot, u, f, E)
    for b in range(B):
        single = pd_step(model, q[b:b + 1], qdot[b:b + 1], u[b:b + 1], f[b:b + 1], E[b:b + 1])
        for x, y in zip(batch, single):
            torch.testing.assert_close(x[b:b + 1], y, atol=1e-9, rtol=0)


def test_actuated_fish_shows_a_head_to_tail_travelling_wave(coarse_mesh):
    model = SolidModel(coarse_mesh)
    ctrl = WaveController.default(coarse_mesh.length, C=PAPER_C)
    L, f = coarse_mesh.length, 5.0
    stations = np.linspace(0.0, 0.9, 10) * L
    P = coarse_mesh.points
    midline = [int(np.argmin((P[:, 0] - x) ** 2 + P[:, 1] ** 2)) for x in stations]
    q, qdot = rest_state(model)
    ys, steps = [], 80
    with torch.no_grad():
        for k in range(steps):
            q, qdot = pd_step(model, q, qdot, ctrl.contraction(model, k * model.h))
            ys.append(q[0, midline, 1].numpy() - P[midline, 1])
    ys, t = np.array(ys), model.h * np.arange(1, steps + 1)
    # phase of the lateral displacement over the last two periods: y ~ a + A cos(w t - phi)
    last = t > t[-1] - 2 / f
    w = 2 * math.pi * f
    basis = np.stack([np.ones(last.sum()), np.cos(w * t[last]), np.sin(w * t[last])], 1)
    coef = np.linalg.lstsq(basis, ys[last], rcond=None)[0]
    phase = np.unwrap(np.arctan2(coef[2], coef[1]))
    assert np.all(np.diff(phase) < 0)               # a point nearer the head peaks earlier ...
    assert phase[0] - phase[-1] > math.pi           # ... by most of a wavelength over the body
    # tail excursion grows from zero with the activation ramp (t_a = 0.2 s)
    tail = ys[:, 0]
    window = lambda t0, t1: np.ptp(tail[(t > t0) & (t <= t1)])
    assert abs(tail[0]) < 0.02 * window(0.6, 0.8)
    assert window(0.0, 0.2) < window(0.2, 0.4) < window(0.6, 0.8)
    assert window(0.6, 0.8) > 0.05 * L
