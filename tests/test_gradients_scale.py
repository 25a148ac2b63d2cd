"""Gradients at a reduced but not trivial scale: the real (graded) fish on a 48 x 144 grid, 60
frames, d(head x displacement)/d(frequency) by autograd through the checkpointed rollout against
central finite differences, for both fluids.

The numerical fluid runs on 5 mm cells with the coupling's widths scaled with the grid (sigma, xi,
tau and sigma' are areas: x (5/2.5)^2), so that the mask and the IBM kernel resolve the body as at
full scale. HydroNet runs on the 2.5 mm cells it was trained for (a 12 x 36 cm tank; on 5 mm cells
it would extrapolate), the shipped model with its own pressure (the default); the recovered
pressure has its own check at the end. The solid is solved to atol = 1e-9 N (the default is
1e-8 N; at the former 1e-5 N its stopping noise in J, ~1e-9 m, was 0.1 % of the central
difference at a 1e-5 step, too much for a 1e-3 check of the finite difference itself, and at
HydroNet's steps of 1e-7 and 1e-8 the tighter tolerance matters); autograd is the derivative of
the converged map.
"""

import pytest
import torch

from benchmarks.gradcheck import autograd_at, central_differences
from fishsim.config import load_config
from fishsim.optimize.problem import Problem, Space

COMMON = ["frames=60", "params.frequency.lower=0.5", "params.frequency.upper=20", "solid.pd.atol=1e-9"]
FLUIDS = {"numerical": ["fluid=numerical", "tank.H=48", "tank.W=144", "tank.dx=5e-3", "origin=[0.2,0.12]",
                        "coupling.sigma=2e-6", "coupling.xi=2e-6", "coupling.tau=2e-6", "coupling.sigma_prime=2.5e-5"],
          "hydronet": ["fluid=hydronet", "tank.H=48", "tank.W=144", "origin=[0.1,0.06]"]}
F0 = 5.0                      # Hz; the numerical fluid's central differences at a 1e-6 relative step
                              # (the episode's J is curved enough that 1e-5 is 0.7 % off, 1e-4 0.9 %)
STEP = 1e-7                   # HydroNet's relative step (its map is rough on coarser scales, below)


def problem(fluid: str, dtype: str, device: str = "cpu", extra=()) -> tuple[Problem, Space]:
    cfg = load_config("optimize", [*COMMON, *FLUIDS[fluid], *extra, f"fluid.dtype={dtype}", f"device={device}"])
    space = Space(list(cfg.params), list(cfg.params.values()))
    return Problem(cfg, space, cfg.objective), space


def autograd(pr: Problem, space: Space) -> float:
    return autograd_at(pr, space, F0)[1]


@pytest.fixture(scope="module", params=list(FLUIDS))
def reference(request):
    """(fluid, float64 problem, its central differences at F0 in float64 (numerical: the 1e-6
    step; HydroNet: STEP), the float64 autograd gradient on one thread), computed once
    for the tests below."""
    import numba

    pr, space = problem(request.param, "float64")
    fd = central_differences(pr, space, F0, (1e-6 if request.param == "numerical" else STEP,))
    before = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    try:
        grad = autograd(pr, space)
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])
    return request.param, pr, space, fd, grad


def test_float64_gradient_matches_central_differences(reference):
    """Within 1e-3 of every central difference computed. The numerical fluid: the 1e-6 step
    (measured at the defaults since 2026-11-29, later: the joint stage at 4 sub-steps, ratio 6.75,
    no force ramp: differences 1.27504 / 1.27776 / 1.28684 / 1.28671 e-2 at steps 1e-4 / 1e-5 /
    1e-6 / 1e-7, autograd 1.28671e-2, 0.9 / 0.7 / 0.01 / 0.00004 % from them: the map is curved
    on the 1e-5 step's scale; at ratio 6.5 with the paper's 20-frame force ramp 1.13830 / 1.13958 /
    1.13988 e-2 at 1e-4 / 1e-5 / 1e-6, autograd 1.13985e-2; at ratio 7 the 1e-4 step was 3.7 %
    off. With the split passes (8 x 3) and the IBM weight "outside": 1.4481 / 1.4733 / 1.4710 / 1.4723 / 1.4875
    e-2 at steps 1e-3 to 1e-7, autograd 1.4705e-2). HydroNet's map is rough on coarser scales (a ReLU network is
    piecewise linear, so a step crosses activation kinks): with the model shipped 2026-11-30 and the
    symmetric step, differences 1.04222 / 1.04289 / 1.04305 e-2 at steps 1e-6 / 1e-7 / 1e-8,
    autograd 1.04304e-2: 0.08 / 0.015 / 0.0004 % from them (the model before: 9.4077 / 9.3503 /
    9.3676 / 9.3622 / 9.3698 e-3 at steps 1e-5 to 1e-9, autograd 9.3626e-3). (Before the solid's
    line search took the approximate Wolfe test, its stalled solves left noise of several per cent
    in the 1e-8 and 1e-9 differences.)"""
    fluid, _, _, fd, grad = reference
    for value in fd:
        assert abs(grad - value) <= 1e-3 * abs(value), (fluid, fd, grad)


def test_float32_gradient_is_within_its_rounding_of_float64(reference):
    """float32, the default: the fluid's rounding and, for the numerical fluid, its joint solves'
    looser tolerances (1e-3, adjoint 1e-4; float64 1e-6: fishsim/fluid/numerical.py IMMERSE_TOL)
    move the 60-frame gradient by 4.0e-4 (numerical; 3.5e-4 with the Schwarz overlap 4 in place
    of 12, 6e-6 with every solve to 1e-6, 1.0e-3 with the adjoint's at 1e-3, 1.6e-2 with the
    predictor stage's alone at 1e-2) and 1.1e-3 (HydroNet, the model shipped 2026-11-30 and its
    symmetric step; 1.9e-3 with the model before) relative (measured), so the float32
    gradient also agrees with the float64 central differences within 1e-3 (numerical) and 3e-3 (HydroNet; the float32 map's own
    differences need steps >= 1e-3, where the map's curvature shows). HydroNet's rounding moves
    which of the ReLU network's kinks the 60 frames cross, so its size depends on the summation
    order: 4e-5 with NCHW convolutions, 1.9e-3 with the NHWC ones run since 2026-11-28 (7e-4 with
    the former IBM weight; both with the model shipped before 2026-11-30), within the spread of
    that model's central differences over steps 1e-5 to 1e-9 (0.6 %, test above)."""
    fluid, _, _, fd, grad64 = reference
    pr, space = problem(fluid, "float32")
    grad32 = autograd(pr, space)
    tolerance = 1e-3 if fluid == "numerical" else 3e-3
    assert abs(grad32 - grad64) <= tolerance * abs(grad64), (grad32, grad64)
    for value in fd:
        assert abs(grad32 - value) <= tolerance * abs(value), (fluid, fd, grad32)


@pytest.mark.parametrize("fluid", list(FLUIDS))
def test_gradient_is_bitwise_repeatable_and_thread_count_independent(fluid):
    """Determinism (float64, the first 20 frames of the episode): the same inputs give the same
    gradient bit for bit in a second run, and two threads (torch's reductions and numba's sample
    loops) the one-thread gradient within 1e-10 relative, with either fluid. (HydroNet's differed
    by 1.5e-7 over 60 frames, then 1e-9, while its 1x1 output convolution ran as a BLAS product
    whose last bit depended on the thread count, which the solid's tolerance-stopped solve carried
    on; measured 0.0 since it runs in a fixed order.)"""
    import numba

    pr, space = problem(fluid, "float64", extra=["frames=20"])
    first, second = autograd(pr, space), autograd(pr, space)
    assert first == second, (first, second)
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("NUMBA_NUM_THREADS < 2 (OMP_NUM_THREADS=1): one thread only")
    torch.set_num_threads(2)
    numba.set_num_threads(2)
    two = autograd(pr, space)
    assert abs(two - first) <= 1e-10 * abs(first), (fluid, first, two)


def test_recovered_pressure_gradient_matches_central_differences():
    """HydroNet's recovered pressure, computed from its velocities by a PCG solve to
    fluid.pressure_tol (1e-6): autograd (implicit differentiation of the solve) within 1e-3 of the
    central difference at a 1e-7 step (measured 2026-11-30, the shipped model and the defaults of
    that day: autograd 4.42576e-3, differences 4.39174 / 4.42277 / 4.42645 / 4.42569 e-3 at steps
    1e-5 / 1e-6 / 1e-7 / 1e-8, 0.77 / 0.068 / 0.016 / 0.0014 % from it). With the former
    tolerance, 1e-2, the solve depended on its warm start, which the implicit gradient does not
    see: autograd was 1.04 % off on the 5 mm grid with the model shipped before 2026-11-26, and
    2.8x off over 100 frames at full scale (README "Gradients"); with the model shipped then the
    map was rough at steps of 1e-4 and 1e-5 (differences 7.283 / 5.481 e-4 against 5.727 to
    5.635 e-4 at 1e-6 to 1e-9)."""
    pr, space = problem("hydronet", "float64", extra=["fluid.pressure=recovered"])
    (fd,) = central_differences(pr, space, F0, (1e-7,))
    grad = autograd(pr, space)
    assert abs(grad - fd) <= 1e-3 * abs(fd), (fd, grad)


def test_wall_fit_gradient_matches_central_differences():
    """``coupling.ibm_fit=wall`` (the surface pressure's normal slope imposed from each node's
    acceleration a frame late, so the force depends on qdot_t - qdot_t-1 too), numerical fluid,
    float64: autograd within 1e-3 of the 1e-6 central difference (measured 1.241872e-2 against
    1.2418721e-2; 1.24157 / 1.24185 e-2 at steps 1e-5 / 1e-7)."""
    pr, space = problem("numerical", "float64", extra=["coupling.ibm_fit=wall"])
    (fd,) = central_differences(pr, space, F0, (1e-6,))
    grad = autograd(pr, space)
    assert abs(grad - fd) <= 1e-3 * abs(fd), (fd, grad)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_cuda_gradient_matches_cpu(reference, dtype):
    """The same episode on CUDA (TF32 off, fishsim's setting there): its gradient within 1e-4 of
    the CPU's in float64 (measured on an H200: 1.2e-6 numerical, 3.1e-5 HydroNet, the fluids'
    rounding carried on by the solid's tolerance-stopped solve) and within 1 % in float32."""
    fluid, _, _, _, cpu64 = reference
    cpu = cpu64 if dtype == "float64" else autograd(*problem(fluid, dtype))
    cuda = autograd(*problem(fluid, dtype, "cuda"))
    assert not torch.backends.cudnn.allow_tf32 and not torch.backends.cuda.matmul.allow_tf32
    assert abs(cuda - cpu) <= (1e-4 if dtype == "float64" else 1e-2) * abs(cpu), (cpu, cuda)
