"""The paper's travelling-wave muscle controller (App. B) and its antagonistic muscle mapping.

    h(X, t) = C v(X) sin(gamma X + omega t) (1 - exp(-t / t_a))
    v(X)    = 4/(25 L) X^2 - 6/25 X + L/10              (m; L/10 at the tail X = 0)

X = 0 is the tail, so lines of constant phase gamma X + omega t = const move towards smaller X:
the wave travels head -> tail with speed omega / gamma. h is a muscle contraction (a fraction),
so C has units 1/m: the tail's contraction amplitude is C L / 10.

Antagonistic mapping: top muscles (Y > 0) contract by max(0, h), bottom muscles by max(0, -h);
h > 0 shortens the top side and bends the body towards +Y there. A layer element holding both
(the thin tail, muscles.py) contracts by top_share max(0, h) + (1 - top_share) max(0, -h). X of
a muscle is its element's centroid.

Calibrated amplitudes, one per muscle model (muscles.py), each in vacuum at 5 Hz with the default
material (E = 6e5 Pa, k_m = E, no volume term) on that model's default fish mesh, so that the tail
tip's peak-to-peak lateral excursion over the second half of a 120-frame episode (`fishsim
simulate fluid=none frames=120`'s summary) is 30.0 mm = 0.15 L, the middle of docs/physics.md's
0.1-0.2 L:
- DEFAULT_C = 12.1 1/m for the default muscle layer (thickness 0.3 of the local half-width,
  X in [0.05, 0.95] L) on the graded mesh (2 mm edges, at least 6 elements across the rear body,
  1803 nodes): 30.1 mm (30.07 mm, and 29.84 mm at 12.0, on the 1775-node mesh the default fish
  had on AVX-512 machines before the mesher's outline was snapped). The stroke is
  mesh-converged: 31.2 / 31.2 / 31.2 / 31.5 mm at 3 / 2 / 1.4 / 1 mm edges and C = 12.6 (README,
  `fishsim validate suite=solid`).
  On the paper's uniform mesh (fish.elements_across=2), where linear triangles are too stiff in
  the thin rear body, C = 12.6 gave 30.0 mm at 2 mm and converged slowly (28.2 / 30.0 / 30.9 /
  31.4 mm); the project's results before the graded mesh were measured there.
- PAPER_C = 35 1/m for the paper's station muscles on the paper's uniform mesh (largest
  contraction 0.36; the envelope's tail value C L/10 = 0.7 lies behind the first muscle at
  X = 0.05 L): 30.0 mm on the 2 mm mesh only (45.6 / 30.1 / 16.7 / 9.2 mm at 3 / 2 / 1.4 / 1 mm;
  on today's snapped meshes 48.8 / 30.6 / 16.7 / 9.0 mm: one element across, mesh-dependent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from fishsim.solid.model import SolidModel

# Calibrated amplitudes (1/m): tail peak-to-peak excursion 30.0 mm = 0.15 L at 5 Hz in vacuum on
# the default mesh (module docstring), with the default muscle layer and with the paper's stations.
DEFAULT_C = 12.1
PAPER_C = 35.0


def calibrated_amplitude(muscles: str) -> float:
    """The calibrated C (1/m) of a muscle model: 'layer' (DEFAULT_C) or 'paper' (PAPER_C)."""
    return PAPER_C if muscles == "paper" else DEFAULT_C


def envelope(X: torch.Tensor, length: float) -> torch.Tensor:
    """v(X) = 4/(25 L) X^2 - 6/25 X + L/10 in metres (X in metres, X = 0 at the tail)."""
    return 4.0 / (25.0 * length) * X**2 - 6.0 / 25.0 * X + length / 10.0


def wave_signal(X: torch.Tensor, t, C: torch.Tensor, omega: torch.Tensor, gamma: torch.Tensor,
                length: float, t_a: float, t_anchor: float = 0.0) -> torch.Tensor:
    """h(X, t) [B, n] for element positions X [n] (m), time t (s, scalar or [B]), amplitude
    C [B] (1/m), angular frequency omega [B] (rad/s), wave number gamma [B] (rad/m).

    t_anchor (s): the phase reached at t_anchor is a constant to autograd, so
    d(omega t)/d(omega) = t - t_anchor (the value is unchanged): truncated backpropagation
    freezes the gait's phase at each cut together with the rest of the state."""
    t = torch.as_tensor(t, dtype=X.dtype, device=X.device).reshape(-1, 1)
    ramp = 1.0 - torch.exp(-t / t_a)
    wt = omega[:, None] * t if not t_anchor else (omega.detach()[:, None] * t_anchor
                                                   + omega[:, None] * (t - t_anchor))
    phase = gamma[:, None] * X[None, :] + wt
    return C[:, None] * envelope(X, length)[None, :] * torch.sin(phase) * ramp


def antagonistic_contraction(h: torch.Tensor, top: torch.Tensor) -> torch.Tensor:
    """Contraction [B, n]: max(0, h) for top muscles, max(0, -h) for bottom ones; top [n] is a bool
    mask or each muscle's top share s in [0, 1] (s max(0, h) + (1 - s) max(0, -h))."""
    if top.dtype == torch.bool:
        return torch.where(top[None, :], torch.relu(h), torch.relu(-h))
    return top[None, :] * torch.relu(h) + (1 - top[None, :]) * torch.relu(-h)


@dataclass(frozen=True)
class WaveController:
    """Controller parameters of a batch, each a [B] tensor (differentiable if it requires grad).

    C: amplitude (1/m). omega: angular frequency (rad/s). gamma: wave number (rad/m).
    t_a: activation ramp time (s, a float shared by the batch). t_anchor: time (s) whose phase
    autograd treats as given (wave_signal; set by truncated backpropagation, else 0).
    """

    C: torch.Tensor
    omega: torch.Tensor
    gamma: torch.Tensor
    t_a: float = 0.2
    t_anchor: float = 0.0

    @staticmethod
    def default(length: float = 0.2, batch: int = 1, frequency: float = 5.0, C: float = DEFAULT_C,
                dtype=torch.float64, device="cpu") -> WaveController:
        """The documented defaults: C = DEFAULT_C, gamma = 2 pi / L, omega = 2 pi frequency."""
        full = lambda v: torch.full((batch,), float(v), dtype=dtype, device=device)
        return WaveController(full(C), full(2 * math.pi * frequency), full(2 * math.pi / length))

    def peak_contraction(self, model: SolidModel) -> torch.Tensor:
        """Largest contraction [B] any muscle of `model` can reach: max over muscles of C v(X)."""
        X = torch.as_tensor(model.fem.centroid_X[model.muscles], dtype=self.C.dtype, device=self.C.device)
        return (self.C[:, None] * envelope(X, model.mesh.length)[None, :]).amax(1)

    def contraction(self, model: SolidModel, t, top_share: torch.Tensor | None = None) -> torch.Tensor:
        """Muscle contraction [B, n_act] of `model`'s muscles at time t (s); X of a muscle is its
        element centroid's material X. top_share [n_act]: the muscles' top shares (default the
        model's; pass a tensor to differentiate through them, e.g. muscles.layer_fractions')."""
        X = torch.as_tensor(model.fem.centroid_X[model.muscles], dtype=self.C.dtype, device=self.C.device)
        if top_share is None:
            top_share = torch.as_tensor(model.muscle_top_share, dtype=self.C.dtype, device=self.C.device)
        h = wave_signal(X, t, self.C, self.omega, self.gamma, model.mesh.length, self.t_a, self.t_anchor)
        return antagonistic_contraction(h, top_share)
