"""From surface-node forces to the solid's external force vector f_ext (paper Secs. 3.4, 4.4)."""

from __future__ import annotations

from torch import Tensor

from fishsim.coupling.config import AVERAGE, PER_NODE


def burn_in_scale(step: int, n_burn_in: int) -> float:
    """Burn-in factor min(1, t / N_burn-in) for time step t = 0, 1, ... (paper Sec. 3.4);
    1 when n_burn_in = 0."""
    if n_burn_in <= 0:
        return 1.0
    return min(1.0, max(step, 0) / n_burn_in)


def fext_from_surface(f_surface: Tensor, surface_idx: Tensor, n_nodes: int,
                      mode: str = PER_NODE, fix_lateral: bool = False,
                      scale: float = 1.0, mass: Tensor | None = None) -> Tensor:
    """External force on every mesh node, [B, N, 2] N (per unit depth).

    f_surface: forces on the surface nodes [B, S, 2]; surface_idx: their mesh indices [S].
    mode "per_node": f_ext[surface_idx] = f_surface, 0 on interior nodes (free swimming).
    mode "average": the total F = sum_k f_k shared by the nodes in proportion to their masses,
        f_i = F m_i / M (the paper's averaged thrust, Sec. 4.4): every node gets the same
        acceleration F / M, so the total force is unchanged and no torque about the centre of
        mass and no deformation is applied. The paper divides by the node count, f_i = F / N
        (``mass`` None: the same for equal masses); on a graded mesh that exerts the torque
        (x_mean - x_c) x F (the default fish: node mean 3.3 cm behind its centre of mass).
    fix_lateral: drop the y component ("x-axis fixed", Sec. 4.4).
    scale: multiplies the result (the burn-in factor ``burn_in_scale``).
    mass: lumped node masses [N] (kg per unit depth), used by mode "average"; None: equal.
    """
    B = f_surface.shape[0]
    if mode == PER_NODE:
        f = f_surface.new_zeros(B, n_nodes, 2).index_copy(1, surface_idx, f_surface)   # a polyline's nodes differ
    elif mode == AVERAGE:
        total = f_surface.sum(1, keepdim=True)
        f = (total / n_nodes).expand(B, n_nodes, 2) if mass is None else total * (mass / mass.sum()).to(total)[:, None]
    else:
        raise ValueError(f"mode must be 'per_node' or 'average', got {mode!r}")
    if fix_lateral:
        f = f * f.new_tensor([1.0, 0.0])
    return f if scale == 1.0 else f * scale
