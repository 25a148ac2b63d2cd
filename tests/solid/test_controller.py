"""The travelling-wave controller (paper App. B) and the antagonistic muscle mapping."""

import math

import numpy as np
import pytest
import torch

from fishsim.mesh.fish_mesh import ACTUATOR_TOP
from fishsim.solid import SolidModel
from fishsim.solid.controller import WaveController, antagonistic_contraction, envelope, wave_signal


def test_envelope_values():
    L = 0.2
    X = torch.tensor([0.0, 0.75 * L, L], dtype=torch.float64)
    torch.testing.assert_close(envelope(X, L), torch.tensor([L / 10, 0.01 * L, 0.02 * L], dtype=torch.float64))


def test_antagonistic_muscles_never_contract_together():
    h = torch.tensor([[0.3, -0.2, 0.0, 0.1]])
    top = torch.tensor([True, True, False, False])
    u = antagonistic_contraction(h, top)
    torch.testing.assert_close(u, torch.tensor([[0.3, 0.0, 0.0, 0.0]]))
    torch.testing.assert_close(antagonistic_contraction(h, ~top), torch.tensor([[0.0, 0.2, 0.0, 0.1]]))


def test_wave_travels_from_head_to_tail():
    L = 0.2
    C, omega, gamma = (torch.tensor([v], dtype=torch.float64) for v in (10.0, 2 * math.pi * 5, 2 * math.pi / L))
    X = torch.linspace(0, L, 2001, dtype=torch.float64)
    crest = lambda t: X[torch.argmax(wave_signal(X, t, C, omega, gamma, L, 0.2)[0] / envelope(X, L))]
    # the crest of sin(gamma X + omega t) moves towards X = 0 (the tail) at omega / gamma
    x0, x1 = crest(1.0), crest(1.01)
    assert abs((x0 - x1).item() - 0.01 * 5 * L) < 1e-3       # 10 mm in 0.01 s, towards the tail


def test_ramp_starts_at_zero():
    ctrl = WaveController.default()
    h = wave_signal(torch.linspace(0, 0.2, 5, dtype=torch.float64), 0.0, ctrl.C, ctrl.omega, ctrl.gamma, 0.2, 0.2)
    assert torch.all(h == 0)


def test_contraction_is_differentiable_in_C_omega_gamma(coarse_mesh):
    model = SolidModel(coarse_mesh)
    params = [torch.tensor([v, v * 1.1], dtype=torch.float64, requires_grad=True)
              for v in (35.0, 2 * math.pi * 5, 2 * math.pi / 0.2)]

    def f(C, omega, gamma):
        return WaveController(C, omega, gamma).contraction(model, 0.37)

    assert torch.autograd.gradcheck(f, params)
    u = f(*params)
    assert u.shape == (2, model.n_muscles) and bool((u >= 0).all()) and bool((u < 1).all())
    top = np.asarray(coarse_mesh.actuator)[model.muscles] == ACTUATOR_TOP
    assert bool((u[:, top] > 0).any()) and bool((u[:, ~top] > 0).any())


def test_anchored_phase_keeps_the_value_and_differentiates_from_the_anchor():
    """With t_anchor, h is unchanged and dh/domega = C v(X) cos(gamma X + omega t) ramp (t - t_anchor):
    the phase reached at t_anchor is a constant."""
    X = torch.linspace(0, 0.2, 7, dtype=torch.float64)
    C, gamma = torch.tensor([12.0], dtype=torch.float64), torch.tensor([31.4], dtype=torch.float64)
    omega = torch.tensor([2 * math.pi * 5], dtype=torch.float64, requires_grad=True)
    t, t_a, anchor = 0.73, 0.2, 0.5
    plain = wave_signal(X, t, C, omega, gamma, 0.2, t_a)
    h = wave_signal(X, t, C, omega, gamma, 0.2, t_a, t_anchor=anchor)
    torch.testing.assert_close(h, plain, rtol=1e-14, atol=1e-16)
    (g,) = torch.autograd.grad(h.sum(), omega)
    phase = gamma * X + omega.detach() * t
    expected = (C * envelope(X, 0.2) * torch.cos(phase) * (1 - math.exp(-t / t_a)) * (t - anchor)).sum()
    assert float(g) == pytest.approx(float(expected), rel=1e-12)
