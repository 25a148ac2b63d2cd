"""Differentiable projective-dynamics solid (docs/physics.md section 3; DiffPD, Du et al. 2021).

    model = SolidModel(mesh, SolidMaterial(), h=0.01)              # never changes afterwards
    q, qdot = rest_state(model, batch=B)
    cache = SolverCache()                                           # what the solve carries between steps
    for k in range(steps):
        q, qdot = pd_step(model, q, qdot, contraction, f_ext, E, cache=cache)   # [B, N, 2] each

`controller.muscle_contraction` turns the paper's travelling-wave controller into `contraction`.
"""

from fishsim.lazy import exports

__getattr__, __all__ = exports(__name__, {
    "config": ("PDOptions", "SolidMaterial"),
    "fem": ("FemQuantities", "fem_quantities"),
    "model": ("SolidModel", "SolverCache"),
    "solve": ("ForwardInfo",),
    "step": ("pd_step", "predicted_start", "rest_state"),
})
