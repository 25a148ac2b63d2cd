"""Prototype (not kept; docs/validation.md, "Sub-iterations that settle"): the explicit frame with an
anisotropic added-mass stabilisation M^ = r m_k (P_k + BETA (I - P_k)), P_k the projection on the
fish's lateral axis ("lateral") or on each node's local midline normal ("local"), solved by
iterating the solid with the frame's fluid force fixed (Aitken-relaxed) until the velocities
change by < 1e-6: the PD step with that mass. Prints the study's head x displacements [mm].

    PYTHONPATH=. python results/convergence/2026-12-01-anisotropic/anisotropic.py K MODE FRAMES [BETA]
"""
import sys, time, json
import torch
import fishsim.rollout as R
from fishsim.coupling.added_mass import body_axis, aitken_relaxed
from fishsim.solid import pd_step as _pd
from fishsim.swim_study import episode

K = int(sys.argv[1]) if len(sys.argv) > 1 else 30
MODE = sys.argv[2] if len(sys.argv) > 2 else "lateral"
stats = []

orig_frame = R.Swimmer.frame
NBINS = 30
BETA = float(sys.argv[4]) if len(sys.argv) > 4 else 0.0

def local_normal(self, q, mass):
    X = torch.as_tensor(self.solid.mesh.points[:, 0], dtype=q.dtype)
    L = float(self.solid.mesh.length)
    bins = (X / L * NBINS).long().clamp(0, NBINS - 1)
    w = torch.zeros(NBINS, dtype=q.dtype).index_add_(0, bins, mass)
    c = torch.zeros(q.shape[0], NBINS, 2, dtype=q.dtype).index_add_(1, bins, q * mass[None, :, None]) / w[None, :, None]
    t = torch.empty_like(c)
    t[:, 1:-1] = c[:, 2:] - c[:, :-2]
    t[:, 0], t[:, -1] = c[:, 1] - c[:, 0], c[:, -1] - c[:, -2]
    t = t / t.norm(dim=-1, keepdim=True)
    tn = t[:, bins]
    return torch.stack((-tn[..., 1], tn[..., 0]), -1)

def frame(self, state, params, t, start=None, muscles=None, cache=None, timer=None):
    new, out = orig_frame(self, state, params, t, start, muscles, cache, timer)
    if state.qdot_prev is None or self.added_mass is None:
        return new, out
    h = self.h
    mass = self.node_mass(state.q)
    Mh = self.added_mass.to(state.q)[None, :, None]
    axis = body_axis(state.q, mass)
    e = torch.stack((-axis[..., 1], axis[..., 0]), -1)          # lateral unit [B,1,2]
    if MODE == "local":
        e = local_normal(self, state.q, mass)
    proj = lambda v: (v * e).sum(-1, keepdim=True) * e
    a_t = (state.qdot - state.qdot_prev) / h
    if muscles is None:
        muscles = self.muscle_weights(params)
    weight = None if muscles is None else muscles[0]
    contraction, f_ext = out.contraction, out.f_ext
    q, qdot = new.q, new.qdot
    relax = None
    for k in range(K):
        a_k = (qdot - state.qdot) / h
        stab = Mh * (proj(a_t) + BETA * (a_t - proj(a_t)) + (1 - BETA) * (a_k - proj(a_k)))
        _, qdot_pass = _pd(self.solid, state.q, state.qdot, contraction, f_ext + stab, params.E, start=q,
                           muscle_weight=weight, cache=cache)
        change = (qdot_pass - qdot).abs().max() / qdot.abs().max()
        qdot, relax = aitken_relaxed(qdot, qdot_pass, relax)
        q = state.q + h * qdot
        if change < 1e-6:
            break
    stats.append((k + 1, float(change)))
    return R.SwimState(q, qdot, new.fluid, state.qdot, new.tunnel), out

R.Swimmer.frame = frame
frames = int(sys.argv[3]) if len(sys.argv) > 3 else 120
t0 = time.time()
res = episode([], [3, 5, 7], frames)
its = [s[0] for s in stats]
print(json.dumps({"K": K, "displacement_mm": res["displacement_mm"], "drift": res["lateral_drift_mm"],
                  "failures": res["failures"], "mean_its": sum(its) / len(its), "max_its": max(its),
                  "last_change_max": max(s[1] for s in stats), "wall": time.time() - t0}))
