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
                      scale: float = 1.0) -> Tensor:
    """External force on every mesh node, [B, N, 2] N (per unit depth).

    f_surface: forces on the surface nodes [B, S, 2]; surface_idx: their mesh indices [S].
    mode "per_node": f_ext[surface_idx] = f_surface, 0 on interior nodes (free swimming).
    mode "average": every one of the N nodes gets sum_k f_k / N (the paper's averaged thrust,
        Sec. 4.4), so the total force is unchanged and no torque or deformation is applied.
    fix_lateral: drop the y component ("x-axis fixed", Sec. 4.4).
    scale: multiplies the result (the burn-in factor ``burn_in_scale``).
    """
    B = f_surface.shape[0]
    if mode == PER_NODE:
        f = f_surface.new_zeros(B, n_nodes, 2).index_add(1, surface_idx, f_surface)
    elif mode == AVERAGE:
        f = (f_surface.sum(1, keepdim=True) / n_nodes).expand(B, n_nodes, 2)
    else:
        raise ValueError(f"mode must be 'per_node' or 'average', got {mode!r}")
    if fix_lateral:
        f = f * f.new_tensor([1.0, 0.0])
    return f * scale
