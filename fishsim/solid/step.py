"""`pd_step`: one differentiable implicit-Euler projective-dynamics step of a batch of fish.

    qdot+ = qdot + h M^-1 (f_ext + f_int(q+; u, E)),   q+ = q + h qdot+

solved as q+ = argmin Phi(q) (see solve.py). The step is one `torch.autograd.Function`; its
backward is DiffPD's adjoint, never autograd through the iterations. With lambda the solution of
(A - dA) lambda = b, b = dL/dq+ + dL/dqdot+ / h (A - dA = M/h^2 - df_int/dq at q+):

    dL/dq     = M/h^2 lambda - dL/dqdot+ / h       dL/dqdot = M/h lambda
    dL/df_ext = lambda                              dL/dtheta = lambda^T df_int/dtheta
                                                    = -(G lambda) : dS/dtheta   (theta = u, E)

Device: the solver runs on the CPU in numpy/scipy (float64); tensors on another device are copied
to the CPU and the results back (a few kB per step for the fish, cheaper than a dense GPU solve).
"""

from __future__ import annotations

import numpy as np
import torch

from fishsim.errors import SimulationBlowUp
from fishsim.solid import elastic, kernels
from fishsim.solid.model import SolidModel, SolverCache
from fishsim.solid.solve import ForwardInfo, newton_solve, pd_solve


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().to("cpu", torch.float64).numpy()


def forward_step(model: SolidModel, cache: SolverCache, q, qdot, contraction, f_ext, E,
                 start=None) -> tuple[np.ndarray, np.ndarray, ForwardInfo]:
    """numpy step: q, qdot, f_ext [B, N, 2] (or None), contraction [B, n_act], E [B] -> (q+, qdot+, info);
    cache: the solver's factors kept between steps (pd_solve).

    Target y = q + h qdot + h^2 M^-1 f_ext.  L-BFGS starts from ``start`` [B, N, 2] if given,
    else from the free flight q + h qdot, not from y: h^2 M^-1 f_ext moves single surface nodes
    by up to ~2 mm (an element) under the IBM's nodal forces, which the stiff body then undoes."""
    h = model.h
    free = q + h * qdot
    y = free if f_ext is None else free + h * h * f_ext / model.mass[None, :, None]
    X0 = np.ascontiguousarray(free if start is None else start)
    q_next, info = pd_solve(model, np.ascontiguousarray(y), X0, np.ascontiguousarray(contraction.T), E, cache)
    return q_next, (q_next - q) / h, info


def adjoint_gradients(model: SolidModel, cache: SolverCache, q_next, contraction, E, grad_q_next, grad_qdot_next):
    """numpy backward of one step (its statistics recorded in ``cache.stats``). Returns (dL/dq,
    dL/dqdot, dL/du [B, n_act], dL/df_ext, dL/dE [B])."""
    h = model.h
    contraction = np.ascontiguousarray(contraction.T)
    b = np.ascontiguousarray(grad_q_next + grad_qdot_next / h)
    lam, its, direct = newton_solve(model, q_next, contraction, E, b, cache=cache)
    cache.stats.record_backward(its, direct)
    grad_u, grad_E = parameter_gradients(model, q_next, contraction, E, lam)
    mass = model.mass[None, :, None]
    return mass / h**2 * lam - grad_qdot_next / h, mass / h * lam, grad_u, lam, grad_E


def parameter_gradients(model: SolidModel, q_next: np.ndarray, contraction: np.ndarray, E: np.ndarray,
                        lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dL/du [B, n_act], dL/dE [B]) = -lambda^T d(grad Phi)/d(u, E) at q+ (q_next, lam [B, N, 2];
    contraction [n_act, B], unused: dS/du and dS/dE do not depend on it), compiled
    (kernels.parameter_gradients)."""
    material, area = model.material, model.fem.area
    grad_u, grad_E = np.empty((len(lam), model.n_muscles)), np.empty(len(lam))
    kernels.parameter_gradients(np.ascontiguousarray(q_next), np.ascontiguousarray(lam), model.mesh_triangles,
                                model.fem.grad, area * material.corotated_per_E,
                                area * material.volume_per_E if material.volume_term else np.zeros(0),
                                model.muscle_of, model.muscle_weight, grad_u, grad_E)
    return grad_u, grad_E


def muscle_weight_gradient(model: SolidModel, q_next: np.ndarray, contraction: np.ndarray,
                           grad_u: np.ndarray) -> np.ndarray:
    """dL/dw [n_act] (summed over the batch) for the muscles' PD weights w, from dL/du [B, n_act]
    at q+ [B, N, 2] (contraction [B, n_act]): the fiber stress S = w (|F m| - a) n gives
    dS/dw = (|F m| - a) n = dS/du (|F m| - a) / w, so dL/dw = dL/du (|F m| - a) / w."""
    Z = elastic.deformation_gradients(model, elastic.to_columns(q_next))
    stretch = np.hypot(Z[0, model.muscles, 0], Z[0, model.muscles, 1]).T           # |F m| [B, n_act]
    w = model.muscle_weight
    safe = np.where(w > 0, w, 1.0)
    return np.where(w > 0, (grad_u * (stretch - (1.0 - contraction)) / safe).sum(0), 0.0)


class PDStepFunction(torch.autograd.Function):
    """(q, qdot, contraction, f_ext, E, start, muscle_weight) -> (q+, qdot+); backward by the
    adjoint (module doc), with the model and the SolverCache as leading non-tensor arguments.
    ``start`` (L-BFGS's initial guess, or None) is not differentiated;
    ``muscle_weight`` ([n_act], or None) carries the model's muscle weights for their gradient."""

    @staticmethod
    def forward(ctx, model, cache, q, qdot, contraction, f_ext, E, start=None, muscle_weight=None):
        f = None if f_ext is None else _np(f_ext)
        start = None if start is None else _np(start)
        q_next, qdot_next, info = forward_step(model, cache, _np(q), _np(qdot), _np(contraction), f, _np(E), start)
        cache.stats.record_forward(info.iterations, info.residual)
        if not (np.isfinite(q_next).all() and np.isfinite(qdot_next).all()):
            raise SimulationBlowUp("PD step produced non-finite positions; reduce the time step, the "
                                   "activation or the external force, or raise E")
        ctx.model, ctx.cache, ctx.has_f_ext, ctx.weight_like = model, cache, f_ext is not None, muscle_weight
        out_q, out_qdot = (torch.as_tensor(x, dtype=q.dtype, device=q.device) for x in (q_next, qdot_next))
        ctx.save_for_backward(out_q, contraction, E)
        return out_q, out_qdot

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_q_next, grad_qdot_next):
        q_next, contraction, E = ctx.saved_tensors
        zeros = torch.zeros_like(q_next)
        grads = adjoint_gradients(ctx.model, ctx.cache, _np(q_next), _np(contraction), _np(E),
                                  _np(grad_q_next if grad_q_next is not None else zeros),
                                  _np(grad_qdot_next if grad_qdot_next is not None else zeros))
        like = (q_next, q_next, contraction, q_next, E)
        out = [torch.as_tensor(g, dtype=t.dtype, device=t.device) for g, t in zip(grads, like)]
        if not ctx.has_f_ext:
            out[3] = None
        grad_w = None
        if ctx.needs_input_grad[8]:
            w = ctx.weight_like
            grad_w = torch.as_tensor(muscle_weight_gradient(ctx.model, _np(q_next), _np(contraction), grads[2]),
                                     dtype=w.dtype, device=w.device)
        return (None, None, *out, None, grad_w)


def predicted_start(q: torch.Tensor, qdot: torch.Tensor, qdot_prev: torch.Tensor, h: float) -> torch.Tensor:
    """Second-order guess of q+ for pd_step's ``start``: q + h (2 qdot - qdot_prev), the free
    flight plus the last step's velocity change (muscle and fluid forces vary smoothly in time).
    On the default fish at 5 Hz it cuts L-BFGS from 12.2 to 9.8 iterations per step."""
    return q + h * (2 * qdot - qdot_prev)


def _batch_E(model: SolidModel, E, B: int, like: torch.Tensor) -> torch.Tensor:
    """E as a [B] tensor (Pa): None -> the model's material value, scalar -> broadcast."""
    if E is None:
        E = model.material.youngs_modulus
    E = torch.as_tensor(E, dtype=like.dtype, device=like.device)
    if E.ndim == 0:
        E = E.expand(B)
    if E.shape != (B,):
        raise ValueError(f"E must be a scalar or have shape [B] = [{B}], got {tuple(E.shape)}")
    if not bool((E > 0).all()):
        raise ValueError("Young's modulus E must be positive")
    return E


def pd_step(model: SolidModel, q: torch.Tensor, qdot: torch.Tensor, contraction: torch.Tensor,
            f_ext: torch.Tensor | None = None, E=None, return_info: bool = False,
            start: torch.Tensor | None = None, muscle_weight: torch.Tensor | None = None,
            cache: SolverCache | None = None):
    """Advance a batch of fish by one implicit-Euler PD step of length model.h.

    q, qdot: [B, N, 2] positions (m) and velocities (m/s).
    contraction: [B, n_act] muscle contraction u in [0, 1) per actuated element (model.muscles
        order); the muscle's target stretch along its fiber is a = 1 - u.
    f_ext: [B, N, 2] external nodal forces (N per unit depth), or None for none.
    E: Young's modulus (Pa): None (the material's), a float, or a [B] tensor (differentiable).
    Returns (q+, qdot+), both [B, N, 2], differentiable w.r.t. q, qdot, contraction, f_ext and E;
    with return_info also the ForwardInfo (L-BFGS iterations and residual per sample).
    start: [B, N, 2] positions L-BFGS starts from (default: the free flight q + h qdot); it
    changes q+ only within the solver's tolerance (a checkpoint recomputation passes the
    forward pass's q+, which is then returned without an iteration).
    muscle_weight: [n_act] tensor equal to model.muscle_weight (Pa m^2; the solve uses the
        model's), passed to differentiate through the weights, e.g. muscles.layer_weights of a
        layer thickness that requires grad (the muscles are shared by the batch, so its gradient
        sums over the samples).
    cache: the SolverCache of a sequence of steps (the preconditioner's factors, carried from
        one step to the next, and the solver's statistics); pass the same one to every step of
        a sequence. Default: a fresh one (the step then factorises its preconditioner anew).
    Raises SimulationBlowUp if the step produces non-finite values.
    """
    if q.ndim != 3 or q.shape[1:] != (model.n_nodes, 2) or qdot.shape != q.shape:
        raise ValueError(f"q and qdot must both have shape [B, {model.n_nodes}, 2], got "
                         f"{tuple(q.shape)} and {tuple(qdot.shape)}")
    B = q.shape[0]
    if contraction.shape != (B, model.n_muscles):
        raise ValueError(f"contraction must have shape [B, n_act] = [{B}, {model.n_muscles}], "
                         f"got {tuple(contraction.shape)}")
    if not bool(((contraction >= 0) & (contraction < 1)).all()):
        raise ValueError("muscle contraction must lie in [0, 1) (target stretch 1 - contraction > 0)")
    if f_ext is not None and f_ext.shape != q.shape:
        raise ValueError(f"f_ext must have shape {tuple(q.shape)}, got {tuple(f_ext.shape)}")
    E = _batch_E(model, E, B, q)
    if start is not None and start.shape != q.shape:
        raise ValueError(f"start must have shape {tuple(q.shape)}, got {tuple(start.shape)}")
    if muscle_weight is not None and (muscle_weight.shape != (model.n_muscles,) or not np.allclose(
            _np(muscle_weight), model.muscle_weight, rtol=1e-12, atol=0)):
        raise ValueError("muscle_weight must equal model.muscle_weight (shape [n_act]); build a model with "
                         "those muscles instead")
    cache = SolverCache() if cache is None else cache
    q_next, qdot_next = PDStepFunction.apply(model, cache, q, qdot, contraction, f_ext, E,
                                             None if start is None else start.detach(), muscle_weight)
    if return_info:
        stats = cache.stats
        return q_next, qdot_next, ForwardInfo(stats.forward_iterations, stats.forward_residual,
                                              stats.forward_residual <= model.options.atol)
    return q_next, qdot_next


def rest_state(model: SolidModel, batch: int = 1, dtype=torch.float64, device="cpu"):
    """(q, qdot) of fish at rest in their material configuration, [B, N, 2] each."""
    q = torch.as_tensor(model.mesh.points, dtype=dtype, device=device).expand(batch, -1, -1).clone()
    return q, torch.zeros_like(q)
