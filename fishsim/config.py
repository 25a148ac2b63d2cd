"""Structured configs: every command's config is a tree of dataclasses, composed by Hydra from
the YAML files in ``fishsim/conf`` and validated here, so an unknown key or an impossible value
fails before any work starts, with one line saying what is wrong.

Each dataclass mirrors the constructor or function it configures; ``validate`` methods check
values that types alone cannot (positivity, ranges) and raise ``ConfigError``.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from fishsim.coupling.config import CouplingConfig
from fishsim.errors import ConfigError
from fishsim.fluid.hydronet.config import PRESSURES, EvalConfig, TrainConfig
from fishsim.fluid.tank import TankConfig
from fishsim.optimize.config import ObjectiveConfig, ParamSpec
from fishsim.render.config import RenderConfig
from fishsim.solid.config import PDOptions, SolidMaterial
from fishsim.swim_study_config import ConvergenceStudyConfig, SwimStudyConfig


def _require(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


def _positive(**values: float) -> None:
    for name, v in values.items():
        _require(v is not None and math.isfinite(v) and v > 0, f"{name} must be > 0 (got {v})")


@dataclass
class FishConfig:
    """The fish body and its mesh (docs/physics.md section 2); see ``fishsim.mesh.make_fish_mesh``."""

    length: float = 0.2
    profile: str = "kern"
    poly_coeffs: list[float] = field(default_factory=list)
    edge_length: float = 2.0e-3
    min_angle: float = 30.0
    actuator_spacing: float = 4.0e-3
    actuator_x_range: list[float] = field(default_factory=lambda: [0.05, 0.95])
    tail_tip_width: float | None = None
    mesh_file: str | None = None
    muscles: str = "layer"
    muscle_thickness: float = 0.3
    elements_across: float | None = None

    def validate(self) -> None:
        _positive(**{"fish.length": self.length, "fish.edge_length": self.edge_length,
                     "fish.actuator_spacing": self.actuator_spacing})
        _require(self.muscles in ("layer", "paper"),
                 f"fish.muscles must be 'layer' or 'paper' (got '{self.muscles}')")
        _require(math.isfinite(self.muscle_thickness) and 0 < self.muscle_thickness <= 1,
                 f"fish.muscle_thickness is a fraction of the local half-width in (0, 1] (got {self.muscle_thickness})")
        _require(self.elements_across is None or (math.isfinite(self.elements_across)
                                                   and 0 <= self.elements_across <= 32),
                 f"fish.elements_across must be null or in [0, 32] (got {self.elements_across}; try 6)")
        _require(self.profile in ("kern", "polynomial"),
                 f"fish.profile must be 'kern' or 'polynomial' (got '{self.profile}')")
        _require(0 < self.min_angle <= 33.8,
                 f"fish.min_angle must be in (0, 33.8] degrees, Triangle's limit (got {self.min_angle})")
        _require(self.edge_length < self.length / 10,
                 f"fish.edge_length={self.edge_length} m is too coarse for a {self.length} m fish")
        lo, hi = self.actuator_x_range
        _require(0 <= lo < hi <= 1, f"fish.actuator_x_range must satisfy 0 <= lo < hi <= 1 (got {lo}, {hi})")

    def mesh_elements_across(self) -> float:
        """``elements_across`` the mesher uses: as set, or by default GRADED_ACROSS (6) for the
        muscle layer and 2 (the paper's uniform mesh, on which PAPER_C is calibrated) for
        ``muscles=paper``."""
        from fishsim.mesh.triangulate import GRADED_ACROSS

        if self.elements_across is not None:
            return float(self.elements_across)
        return 2.0 if self.muscles == "paper" else GRADED_ACROSS


@dataclass
class MeshCommandConfig:
    """``fishsim mesh``: mesh the fish, write it and a preview picture."""

    fish: FishConfig = field(default_factory=FishConfig)
    output: str = "fish.vtu"
    preview: bool = True
    out_dir: str | None = None

    def validate(self) -> None:
        from fishsim.io.mesh_io import writable_format

        self.fish.validate()
        writable_format(self.output)


@dataclass
class SolidConfig:
    """The PD solid: material (paper Sec. 4.1) and solver options (``fishsim.solid.model``)."""

    material: SolidMaterial = field(default_factory=SolidMaterial)
    pd: PDOptions = field(default_factory=PDOptions)


@dataclass
class ControllerConfig:
    """The paper's travelling-wave controller h(X, t) = C v(X) sin(gamma X + omega t)(1 - e^(-t/t_a)).

    frequency: f = omega / (2 pi) in Hz.  amplitude: C in 1/m (h is a muscle contraction); null:
        the value calibrated for ``fish.muscles`` (12.6 for the layer, 35 for the paper's stations;
        fishsim/solid/controller.py).
    wave_number: gamma in rad/m (null: 2 pi / L, one wavelength per body).  t_a: ramp time, s.
    """

    frequency: float = 5.0
    amplitude: float | None = None
    wave_number: float | None = None
    t_a: float = 0.2

    def validate(self) -> None:
        _positive(**{"controller.frequency": self.frequency, "controller.t_a": self.t_a})
        _require(self.amplitude is None or (math.isfinite(self.amplitude) and self.amplitude >= 0),
                 f"controller.amplitude must be a finite value >= 0 or null (got {self.amplitude})")
        _require(self.wave_number is None or self.wave_number > 0, "controller.wave_number must be > 0")


@dataclass
class BatchConfig:
    """Per-fish values for a batch of B fish simulated together (same mesh, same tank size).

    Each list has one entry per fish; B is the longest list, a one-entry list is shared, and an
    empty list takes the controller's / material's value.  Example: ``batch.frequency=[3,4,5,6,7]``.
    """

    frequency: list[float] = field(default_factory=list)
    amplitude: list[float] = field(default_factory=list)
    wave_number: list[float] = field(default_factory=list)
    youngs_modulus: list[float] = field(default_factory=list)

    @property
    def size(self) -> int:
        return max([1] + [len(v) for v in (self.frequency, self.amplitude, self.wave_number, self.youngs_modulus)])

    def validate(self) -> None:
        for name in ("frequency", "amplitude", "wave_number", "youngs_modulus"):
            values = getattr(self, name)
            _require(len(values) in (0, 1, self.size),
                     f"batch.{name} has {len(values)} entries; give 1 or B = {self.size}")
            _require(all(v > 0 for v in values) or name == "amplitude" and all(v >= 0 for v in values),
                     f"batch.{name} values must be positive (got {list(values)})")


@dataclass
class FluidConfig:
    """The fluid in the tank (docs/physics.md section 4), one config per model (the ``fluid``
    config group; ``FLUID_MODELS``): ``fluid=numerical`` (the reference solver), ``hydronet`` (the
    trained U-Net) or ``none`` (the vacuum). Here the keys every model has:

    model: none | numerical | hydronet.
    dtype: precision of the fluid fields and the coupling's fluid side, "float32" (default, fast)
        or "float64" (for finite-difference checks of gradients; HydroNet's weights are cast too).
    """

    model: str = "none"
    dtype: str = "float32"

    def validate(self, key: str = "fluid") -> None:
        _require(self.dtype in ("float32", "float64"), f"{key}.dtype must be float32 or float64 (got '{self.dtype}')")
        _require(self.model in FLUID_MODELS, f"{key}.model must be one of {tuple(FLUID_MODELS)} (got '{self.model}')")
        _require(isinstance(self, FLUID_MODELS[self.model]),
                 f"{key}.model={self.model} needs a {FLUID_MODELS[self.model].__name__} (got a {type(self).__name__})")


@dataclass
class VacuumConfig(FluidConfig):
    """No fluid: no hydrodynamic force, the solid alone (``fishsim.fluid.vacuum.Vacuum``); the
    base's keys only."""


@dataclass
class WaterConfig(FluidConfig):
    """A fluid with a density and a viscosity.

    rho: density, kg/m^3 (per unit area in 2D), in [10, 50]; mu: dynamic viscosity, Pa s.
    """

    rho: float = 50.0
    mu: float = 1.25e-4

    def validate(self, key: str = "fluid") -> None:
        super().validate(key)
        _positive(**{f"{key}.rho": self.rho, f"{key}.mu": self.mu})


@dataclass
class NumericalConfig(WaterConfig):
    """The numerical Navier-Stokes reference (``fishsim.fluid.numerical.NumericalFluid``).

    refinement: internal grid dx / r and sub-steps h / r (1, 2 or 4).
    substeps: sub-steps per frame on the r = 1 grid (r times more on the refined one); a floor
        that the CFL safety net raises per fish. 4 with the joint stage (``implicit``): the
        displacement converged (4 / 8 within 0.2 %), its gradient to a few per cent (2.8 % from
        16 sub-steps' on a 60-frame check: fishsim/fluid/numerical.py). The split passes need 8
        (``implicit=false``).
    cfl: the safety net's largest advective Courant number max|v| dt / dx per sub-step. 0.8 keeps
        4 sub-steps up to 0.8 m/s on the 2.5 mm grid and 8 up to 1.6 m/s: the frequency study's
        7 Hz fish peaks at 1.14 m/s and runs 4-6 sub-steps (per fish; one more or less moves it by
        <= 0.2 % with the joint stage); the scheme stays stable to a Courant number ~1.
    penalization_iterations: penalize -> project passes per stage (K) of the split scheme
        (``implicit=false``). 3 with 8 sub-steps: within 0.2 % of 9 passes and 0.3 % of 16
        sub-steps on the frequency study, 12 % short on a body three cells thick.
    penalization_rate: lambda_p (1/s) of the split scheme's blend, 1 - (1 - b)^(lambda_p dt / K) a
        pass: a band cell relaxes to the body at a rate independent of the sub-steps and grid, and
        the fish converges in both (2400: the blend is b itself at 8 x 3 of a 0.01 s frame; a body
        a few cells thick needs more passes, fishsim/fluid/numerical.py). null: the blend is b at
        any dt (the default until 2026-11-29), the band stiffening with K n.
    brinkman: lambda (1/s) of the rate penalisation solved jointly with the projection, which
        converges in sub-steps (fishsim/fluid/numerical.py); null: the split scheme.
    implicit: solve each stage's penalisation at penalization_rate and its projection jointly
        (the default), the passes' limit (K -> infinity; converged in sub-steps, thin bodies
        included), by a PCG solve a stage (at 4 sub-steps ~1.4-1.8x the 8 x 3 passes' time on
        the paper's Table 1); false: penalization_iterations split passes.
    scheme: advection interpolation, "koren" (third order, TVD limited by min/max: a
        piecewise-smooth frame map) | "albada" (second order, van Albada limiter and upwinding
        written as smooth functions: smoother gradients; fishsim.fluid.grid.albada).
    """

    model: str = "numerical"
    refinement: int = 1
    substeps: int = 4
    cfl: float = 0.8
    penalization_iterations: int = 3
    penalization_rate: float | None = 2400.0
    brinkman: float | None = None
    implicit: bool = True
    scheme: str = "koren"

    def validate(self, key: str = "fluid") -> None:
        super().validate(key)
        _require(self.refinement in (1, 2, 4), f"{key}.refinement must be 1, 2 or 4 (got {self.refinement})")
        _require(1 <= self.substeps <= 64, f"{key}.substeps must be in [1, 64] (got {self.substeps})")
        _require(0 < self.cfl <= 1.5, f"{key}.cfl must be in (0, 1.5] (got {self.cfl})")
        _require(self.scheme in ("koren", "albada"), f"{key}.scheme must be koren or albada (got '{self.scheme}')")
        _require(1 <= self.penalization_iterations <= 16,
                 f"{key}.penalization_iterations must be in [1, 16] (got {self.penalization_iterations})")
        _require(self.penalization_rate is None or self.penalization_rate > 0,
                 f"{key}.penalization_rate must be > 0 (1/s) or null (got {self.penalization_rate})")
        _require(self.brinkman is None or self.brinkman > 0,
                 f"{key}.brinkman must be > 0 (1/s) or null (got {self.brinkman})")
        _require(not self.implicit or (self.penalization_rate is not None and self.brinkman is None),
                 f"{key}.implicit=true (the default) solves for {key}.penalization_rate: set it (not null) "
                 f"and leave {key}.brinkman null, or add {key}.implicit=false for the split schemes")


@dataclass
class HydroNetConfig(WaterConfig):
    """HydroNet, the trained U-Net surrogate (``fishsim.fluid.hydronet.HydroNetFluid``).

    model_file: a trained model (best.pt); null: the shipped fishsim/assets/hydronet.pt.
    bf16: run the U-Net trunk in bfloat16 (faster on CPUs with AMX and on GPUs).
    pressure: "network" (the network's own output, the paper's method) or "recovered" (the
        pressure that best satisfies the momentum equation for the network's velocities,
        fishsim/fluid/pressure.py).
    pressure_tol: relative residual of the pressure recovery's PCG solve.
    strict_range: refuse a run whose rho, mu, dx or h lies outside the range the model was
        trained for (default: a one-line warning; fishsim/fluid/hydronet/trained_range.py).
    symmetric: average the network's step with its mirror image in y (exact y-reflection
        equivariance: no sideways drift of its own, a third less surplus kinetic energy; twice
        the network's cost; ``HydroNetFluid``); false: the network alone (the paper's).
    compile: run the network through torch.compile in gradient-free rollouts on the CPU: "auto"
        (those of 4,000 fish-frames and more, which repay its ~10 s compilation: ~10 % faster),
        true (every one), false (never); results within round-off of the uncompiled network's.
    """

    model: str = "hydronet"
    model_file: str | None = None
    bf16: bool = False
    pressure: str = "network"
    pressure_tol: float = 1e-6
    strict_range: bool = False
    symmetric: bool = True
    compile: bool | str = "auto"

    def validate(self, key: str = "fluid") -> None:
        super().validate(key)
        _require(self.compile in (True, False, "auto"),
                 f"{key}.compile must be true, false or auto (got '{self.compile}')")
        _require(self.pressure in PRESSURES,
                 f"{key}.pressure must be recovered or network (got '{self.pressure}')")
        _require(0 < self.pressure_tol < 1, f"{key}.pressure_tol must be in (0, 1) (got {self.pressure_tol})")


FLUID_MODELS: dict[str, type[FluidConfig]] = {"none": VacuumConfig, "numerical": NumericalConfig,
                                              "hydronet": HydroNetConfig}


@dataclass
class SimulateConfig:
    """``fishsim simulate``: one episode of B fish swimming, written as an HDF5 trajectory.

    frames: number of frames of h seconds.  origin: (x, y) in m of the fish's material origin
    (the tail tip) in the tank.  hold_x: hold the fish's centroid x fixed (the paper's thrust
    set-up; the fish undulates and sways in y but cannot travel; ``fishsim.rollout.Swimmer``).
    hold_y: hold its centroid y fixed too (with hold_x the paper's "centred along the x axis").
    tunnel: a swim tunnel: the fish held in x while the water flows past it at its own
        swimming speed U(t), set by its x momentum (``fishsim.rollout.Swimmer``): steady swimming
        for any number of frames; the speed and distances count the water swum through.
    tank: the tank's grid, walls and inflow (the ``tank`` config group, ``fishsim.fluid.tank``).
    fluid: the fluid model's config (the ``fluid`` config group: ``FLUID_MODELS``).
    fluid_stride: store the fluid fields every k frames.
    flush_every: HDF5 write period (frames). ParaView opens the run through the XDMF sidecar
    written beside the trajectory (fishsim.io.xdmf).
    device: cpu | cuda.  overwrite: replace an existing output (else refused: a finished run is never lost).
    check_resources: refuse a run whose estimated memory exceeds what is available, or, inside a
        SLURM job, whose estimated time exceeds what is left of it (fishsim.resources).
    """

    fish: FishConfig = field(default_factory=FishConfig)
    solid: SolidConfig = field(default_factory=SolidConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    batch: BatchConfig = field(default_factory=BatchConfig)
    tank: TankConfig = field(default_factory=TankConfig)
    fluid: FluidConfig = field(default_factory=NumericalConfig)
    coupling: CouplingConfig = field(default_factory=CouplingConfig)
    frames: int = 200
    h: float = 0.01
    origin: list[float] = field(default_factory=lambda: [0.06, 0.125])
    hold_x: bool = False
    hold_y: bool = False
    tunnel: bool = False
    fluid_stride: int = 5
    flush_every: int = 10
    device: str = "cpu"
    output: str = "trajectory.h5"
    out_dir: str | None = None
    overwrite: bool = False
    check_resources: bool = True

    def validate(self) -> None:
        for part in (self.fish, self.controller, self.batch, self.tank, self.fluid):
            part.validate()
        _require(self.frames >= 1, f"frames must be >= 1 (got {self.frames})")
        _positive(h=self.h)
        _require(self.fluid_stride >= 1 and self.flush_every >= 1, "fluid_stride and flush_every must be >= 1")
        _require(self.device in ("cpu", "cuda") or self.device.startswith("cuda:"),
                 f"device must be cpu or cuda (got '{self.device}')")
        if self.tunnel:
            _require(self.fluid.model != "none", "tunnel=true needs a fluid (fluid=numerical or fluid=hydronet)")
            _require(self.tank.inflow == 0.0, f"tunnel=true sets the inflow itself (the fish's speed); "
                     f"drop tank.inflow={self.tank.inflow}")
        if self.fluid.model != "none":
            Lx, Ly = self.tank.size
            x0, y0 = self.origin
            _require(0 < x0 and x0 + self.fish.length < Lx and 0 < y0 < Ly,
                     f"origin={list(self.origin)} puts the fish outside the {Lx:.3f} x {Ly:.3f} m tank")


@dataclass
class OptimizerConfig:
    """How to optimise (fishsim/optimize/methods.py).

    methods: run each in turn, into <out_dir>/<method>/ (cma, or a torch.optim name: adam, sgd, ...).
    iterations: per method.  budget: fish-frames per method (null: none); an iteration costs
        2 x frames for a gradient method (the forward pass and its checkpoint recomputation) and
        popsize x frames for a CMA-ES generation.
    lr: the gradient method's learning rate in normalised units (z in [0, 1] spans the bounds).
    options: more keyword arguments of the torch.optim optimiser.
    sigma: CMA-ES's initial step in normalised units.  popsize: CMA-ES population (null: pycma's 4 + 3 ln P).
    seed: CMA-ES's random seed.  segment: gradient-checkpoint segment (frames).
    truncate: truncated backpropagation through time, the window in frames (0: the full episode).
    max_batch: the most fish one batched rollout holds (null: a CMA-ES generation is one batch);
        a larger population is evaluated in chunks of this size.
    launcher: where the chunks run: ``local`` (here, one after another) or ``submitit`` (one
        submitit job each, in parallel: a population larger than one machine holds).
    submitit: the submitit executor's options: ``cluster`` (slurm, local or debug; default
        slurm where sbatch exists, else local) and any ``update_parameters`` key (timeout_min,
        cpus_per_task, slurm_partition, mem_gb, ...). Needs the ``sweep`` extra.
    """

    methods: list[str] = field(default_factory=lambda: ["adam"])
    iterations: int = 20
    budget: int | None = None
    lr: float = 0.05
    options: dict[str, Any] = field(default_factory=dict)
    sigma: float = 0.1
    popsize: int | None = None
    seed: int = 0
    segment: int = 25
    truncate: int = 0
    max_batch: int | None = None
    launcher: str = "local"
    submitit: dict[str, Any] = field(default_factory=dict)

    def validate(self) -> None:
        from fishsim.optimize.methods import torch_optimizer

        _require(len(self.methods) >= 1, "optimizer.methods must name at least one method (e.g. [adam, cma])")
        for m in self.methods:
            if m != "cma":
                torch_optimizer(m)
        _require(self.iterations >= 1, f"optimizer.iterations must be >= 1 (got {self.iterations})")
        _require(self.popsize is None or self.popsize >= 2,
                 f"optimizer.popsize must be >= 2 (got {self.popsize}): CMA-ES needs a population to rank")
        _positive(**{"optimizer.lr": self.lr, "optimizer.sigma": self.sigma})
        _require(self.segment >= 1, f"optimizer.segment must be >= 1 (got {self.segment})")
        _require(self.truncate >= 0, f"optimizer.truncate must be >= 0 frames, 0 for none (got {self.truncate})")
        _require(self.max_batch is None or self.max_batch >= 1,
                 f"optimizer.max_batch must be >= 1 fish or null for the whole population (got {self.max_batch})")
        _require(self.launcher in ("local", "submitit"),
                 f"optimizer.launcher must be local or submitit (got {self.launcher!r})")


@dataclass
class OptimizeConfig(SimulateConfig):
    """``fishsim optimize``: the episode (every ``fishsim simulate`` key) plus what to optimise.

    objective: what is maximised (fishsim/optimize/problem.py).  params: {name: bounds, scale,
    start} of the optimised parameters (frequency, amplitude, wave_number, youngs_modulus).
    optimizer: how.  resume: continue the run in out_dir from its last completed iteration.
    """

    frames: int = 120
    objective: ObjectiveConfig = field(default_factory=ObjectiveConfig)
    params: dict[str, ParamSpec] = field(default_factory=dict)   # optimize.yaml: frequency in [0.5, 10.5] Hz
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    resume: bool = False

    def validate(self) -> None:
        super().validate()
        _require(self.batch.size == 1, "batch.* lists are not used by optimize (its candidates are the batch); "
                 "remove them")
        _require(len(self.params) >= 1, "params is empty: give at least one parameter to optimise "
                 "(e.g. +params.frequency={lower:1,upper:10})")
        for name, spec in self.params.items():
            spec.check(name)
        self.objective.check(self.hold_x and not self.tunnel)
        slowest = self.params["frequency"].lower if "frequency" in self.params else self.controller.frequency
        self.objective.check_window(slowest, self.frames, self.h)
        self.optimizer.validate()
        _require(self.resume is False or self.out_dir is not None,
                 "resume=true needs out_dir=<the run folder to continue>")
        b = self.optimizer.budget
        if b is not None:
            for m in self.optimizer.methods:
                cost = self.iteration_cost(m)
                _require(b >= cost, f"optimizer.budget = {b} fish-frames cannot afford one iteration of {m} "
                         f"({cost} fish-frames at frames={self.frames}); raise it or shorten the episode")

    def iteration_cost(self, method: str) -> int:
        """Fish-frames of one iteration of ``method``: 2 x frames for a gradient method (the forward
        pass and its checkpoint recomputation), popsize x frames for a CMA-ES generation (pycma's
        default population 4 + floor(3 ln P) for P parameters)."""
        if method != "cma":
            return 2 * self.frames
        popsize = self.optimizer.popsize or 4 + int(3 * math.log(len(self.params)))
        return popsize * self.frames


# ---------------------------------------------------------------------------------- validate

SUITES = ("hydronet", "solid", "swim", "convergence")
STUDY_FLUIDS = ("none", "numerical", "hydronet")


@dataclass
class SolidStudyConfig:
    """suite=solid (``fishsim.solid_study``). edges: fish edge lengths (m), each a
    `fishsim simulate` run per muscle model (deviations from the finest). muscles: layer and/or
    paper. fluid: none (vacuum) | numerical | hydronet. frames: episode length at h = 0.01 s
    (stroke over the second half). beam_across: the cantilever's elements across its thickness
    (empty: no beam check)."""

    edges: list[float] = field(default_factory=lambda: [3.0e-3, 2.0e-3, 1.4e-3, 1.0e-3])
    muscles: list[str] = field(default_factory=lambda: ["layer", "paper"])
    fluid: str = "none"
    frames: int = 120
    beam_across: list[int] = field(default_factory=lambda: [2, 4, 8, 16])

    def validate(self) -> None:
        if len(self.edges) < 2 or not all(0 < e < 0.02 for e in self.edges):
            raise ConfigError(f"solid.edges needs at least 2 edge lengths in (0, 0.02) m (got {list(self.edges)})")
        if not self.muscles or not set(self.muscles) <= {"layer", "paper"}:
            raise ConfigError(f"solid.muscles must list layer and/or paper (got {list(self.muscles)})")
        if self.fluid not in STUDY_FLUIDS:
            raise ConfigError(f"solid.fluid must be one of {STUDY_FLUIDS} (got '{self.fluid}')")
        if self.frames < 4:
            raise ConfigError(f"solid.frames must be >= 4 (the stroke is measured over the second half; got {self.frames})")
        if not all(n >= 1 for n in self.beam_across):
            raise ConfigError(f"solid.beam_across must be >= 1 element across (got {list(self.beam_across)})")


# validate's settings before its ``hydronet`` node (2026-11-27): top-level keys, now hydronet.*
VALIDATE_HYDRONET_KEYS = ("model_file", "bf16", "pressure")


@dataclass
class ValidateConfig:
    """suite: hydronet | solid | swim | convergence.
    hydronet: the HydroNet being judged, a ``HydroNetConfig`` (conf/fluid/hydronet.yaml, composed
        as ``fluid@hydronet``): its model_file (null: the shipped one), bf16, pressure,
        pressure_tol and strict_range. suite=hydronet builds the evaluated network from it;
        suite=swim's and suite=solid's HydroNet runs take its model_file, bf16, pressure_tol and
        strict_range (suite=solid its pressure too; suite=swim's fluids hydronet and
        hydronet_recovered set their own). Its rho, mu and dtype stay at their defaults: the
        fluid is the scenes' (scenes.rho, scenes.mu) or the studies' runs' (swim.overrides).
    device: cpu | cuda. scenes: the held-out scenes and protocol (hydronet).
    solid: the mesh study and beam check (solid). swim: the frequency study (swim).
    convergence: the frequency study against the reference's knobs (convergence)."""

    suite: str = "hydronet"
    hydronet: HydroNetConfig = field(default_factory=HydroNetConfig)
    device: str = "cpu"
    scenes: EvalConfig = field(default_factory=EvalConfig)
    solid: SolidStudyConfig = field(default_factory=SolidStudyConfig)
    swim: SwimStudyConfig = field(default_factory=SwimStudyConfig)
    convergence: ConvergenceStudyConfig = field(default_factory=ConvergenceStudyConfig)
    out_dir: str | None = None

    def validate(self) -> None:
        self.solid.validate()
        self.swim.validate()
        self.convergence.validate()
        if self.suite not in SUITES:
            raise ConfigError(f"suite must be one of {SUITES} (got '{self.suite}')")
        self._validate_hydronet()
        s = self.scenes
        s.tank.validate()
        if not (s.tank.H >= 32 and s.tank.W >= 32 and s.rho > 0 and s.mu > 0):
            raise ConfigError(f"scenes need a tank of at least 32 x 32 cells (HydroNet's U-Net pools it 4 times) and "
                              f"rho, mu > 0 (got {s.tank.H} x {s.tank.W}, rho {s.rho}, mu {s.mu})")
        if not s.radius < min(s.tank.size) / 4:
            raise ConfigError(f"scenes.radius = {s.radius} m does not fit the {s.tank.H} x {s.tank.W} tank of "
                              f"{s.tank.dx} m cells")
        if not (s.warmup >= 0 and s.steps >= 1 and s.radius > 0 and s.fish_amp > 0 and s.h > 0):
            raise ConfigError("scenes.warmup >= 0, scenes.steps >= 1 and radius, fish_amp, h > 0 are required")
        if not (s.speeds or s.frequencies):
            raise ConfigError("give at least one of scenes.speeds or scenes.frequencies")

    def _validate_hydronet(self) -> None:
        """The judged HydroNet's config, its messages naming hydronet.* (not fluid.*); the fluid's
        keys and the precision are the suites' own."""
        net, shipped = self.hydronet, HydroNetConfig()
        if net.model != "hydronet":
            raise ConfigError(f"hydronet.model must be hydronet: validate judges a HydroNet (got '{net.model}')")
        net.validate("hydronet")
        for key in ("rho", "mu", "dtype"):
            if getattr(net, key) != getattr(shipped, key):
                raise ConfigError(f"hydronet.{key} stays at its default ({getattr(shipped, key)}) in validate: the "
                                  "suites set the fluid and the precision (suite=hydronet: scenes.rho, scenes.mu, "
                                  "float32; suite=swim: swim.overrides=[fluid.rho=...], "
                                  "swim.hydronet_overrides=[fluid.dtype=...])")


ROOTS: dict[str, type] = {"mesh": MeshCommandConfig, "simulate": SimulateConfig, "render": RenderConfig,
                         "train-hydronet": TrainConfig, "validate": ValidateConfig, "optimize": OptimizeConfig}


def config_dir() -> str:
    """The shipped config folder (inside the package, so installed wheels find it)."""
    return str(resources.files("fishsim") / "conf")


def load_config(command: str, overrides: list[str] | None = None, config_file: str | None = None) -> Any:
    """Compose ``conf/<command>.yaml`` with command-line ``key=value`` overrides, check it
    against the command's structured config and return the validated dataclass instance.
    ``config_file``: a YAML config (e.g. a run's stored config, optimize's best.yaml) merged over
    the composed defaults; the ``key=value`` overrides apply on top of it (config groups such as
    ``fluid=hydronet`` are then taken from the file: set their keys instead, ``fluid.model=...``).

    Raises ConfigError (one line) for an unknown key, a wrong type or an impossible value, or a
    missing or unreadable config file.
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException

    overrides = [_run_dir_as_out_dir(o) for o in overrides or []]
    _refuse_hydra_runner_keys(overrides)
    overrides = _open_dict_overrides(ROOTS[command], overrides)
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
            raw = compose(config_name=command, overrides=overrides)
    except (HydraException, OmegaConfBaseException, ValueError) as err:  # ValueError: bad group override
        raise ConfigError(_one_line(err, command)) from None
    if config_file is not None:
        from pathlib import Path

        groups = {d.name for d in Path(config_dir()).iterdir() if d.is_dir()}
        raw = _merge_file(raw, config_file, [o for o in overrides if "=" in o and o.split("=")[0].lstrip("+~") not in groups],
                          command)
    return to_dataclass(command, raw)


NO_SWEEPS = ("for several values give a batch list (batch.frequency=[3,4,5]) or sweep with -m "
             "(fishsim simulate -m controller.frequency=3,5, hydra/launcher=joblib to run jobs in parallel); "
             "fishsim optimize searches parameters")


def _run_dir_as_out_dir(override: str) -> str:
    """Hydra's ``hydra.run.dir=X`` (where a run writes) is fishsim's ``out_dir=X``."""
    key, _, value = override.partition("=")
    return f"out_dir={value}" if key.lstrip("+") == "hydra.run.dir" else override


def _dict_fields(cls, prefix: str = "") -> list[str]:
    """Dotted names of the dict-valued fields (free-form options) of a config dataclass."""
    import typing

    names = []
    for name, hint in typing.get_type_hints(cls).items():
        if typing.get_origin(hint) is dict:
            names.append(prefix + name)
        elif dataclasses.is_dataclass(hint):
            names += _dict_fields(hint, f"{prefix}{name}.")
    return names


def _open_dict_overrides(cls, overrides: list[str]) -> list[str]:
    """The overrides as Hydra must see them, measured against the free-form dict fields of the
    config class ``cls``:

    - ``optimizer.options={betas:[0.9,0.99]}`` or ``optimizer.submitit.cluster=local``: a key
      inside such a field is new to the composed config, which Hydra refuses as unknown; it is
      passed as ``++key=value`` (add or replace).
    - ``~key`` deletes an entry of such a field (``~params.frequency``,
      ``~convergence.knobs.substeps``); any other setting always exists (the schema gives it its
      default back), so deleting it would silently do nothing: ConfigError (one line) instead."""
    open_dicts = _dict_fields(cls)

    def rewrite(o: str) -> str:
        key = o.split("=", 1)[0]
        if o.startswith("~") and not o.startswith("~~") and not any(
                key[1:].startswith(d + ".") for d in open_dicts):
            raise ConfigError(f"config error: '{o}' deletes a setting, which keeps its default: set it instead "
                              f"({key[1:]}=<value>); ~ deletes only entries of "
                              f"{', '.join(open_dicts) or 'free-form options (this command has none)'}")
        inside = "=" in o and not key.startswith(("+", "~")) and any(
            key == d or key.startswith(d + ".") for d in open_dicts)
        return "++" + o if inside else o
    return [rewrite(o) for o in overrides]


def _refuse_hydra_runner_keys(overrides: list[str]) -> None:
    """A single run (no -m) composes its config with Hydra's compose API and runs itself: Hydra's
    job-runner settings (hydra.*, hydra/sweeper, hydra/launcher) would be accepted and silently do
    nothing. ConfigError (one line) instead; with -m they go to Hydra (fishsim.multirun)."""
    for o in overrides:
        key = o.split("=", 1)[0].lstrip("+~")
        if key in ("hydra", "--multirun") or key.startswith(("hydra.", "hydra/")):
            raise ConfigError(f"config error: '{o}' is a setting of Hydra's job runner, used only by sweeps: add -m "
                              f"(fishsim.multirun); {NO_SWEEPS}")


def _merge_file(raw: Any, path: str, dotted: list[str], command: str | None = None) -> Any:
    """raw <- the YAML file (of ``command``, in today's layout: ``_upgraded``) <- the ``key=value``
    overrides (later wins). A file whose fluid is another model than the composed one replaces the
    composed ``fluid`` node (the models' keys differ)."""
    from pathlib import Path

    import yaml

    if not Path(path).is_file():
        raise ConfigError(f"config file {path} does not exist (give the path of a YAML config, e.g. a run's best.yaml)")
    try:
        loaded = _upgraded(OmegaConf.load(path), command)
        dots = OmegaConf.from_dotlist([o.lstrip("+") for o in dotted if not o.startswith("~")])
        OmegaConf.set_struct(raw, False)          # the file may hold keys of other groups; the schema checks them
        model = OmegaConf.select(loaded, "fluid.model")
        if "fluid" in raw and model is not None and model != raw.fluid.get("model"):
            raw.fluid = {}
        return OmegaConf.merge(raw, loaded, dots)
    except (OmegaConfBaseException, ValueError, OSError, yaml.YAMLError) as err:
        raise ConfigError(f"config file {path} is not a readable YAML config: {_one_line(err, command)}") from None


TANK_KEYS = tuple(f.name for f in dataclasses.fields(TankConfig))


# Keys an earlier layout kept elsewhere (before 2026-11-27): (the command, None for any; the node
# they were in, "" the root; the keys; the node that holds them now; whose settings they are).
MOVED_KEYS = ((None, "fluid", TANK_KEYS, "tank", "the tank"),
              ("validate", "", VALIDATE_HYDRONET_KEYS, "hydronet", "the HydroNet validate judges"),
              ("validate", "scenes", TANK_KEYS, "scenes.tank", "the scenes' tank"))


def _moves(command: str | None) -> list[tuple]:
    return [move for move in MOVED_KEYS if move[0] in (None, command)]


def _moved(key: str, command: str | None) -> tuple[str, str] | None:
    """A key of an earlier layout that ``command`` now keeps elsewhere (MOVED_KEYS): (whose
    setting it is, its key today), or None."""
    parent, _, name = key.rpartition(".")
    for _, source, keys, target, whose in _moves(command):
        if parent == source and name in keys:
            return whose, f"{target}.{name}"
    return None


def _node(tree: dict, path: str, create: bool = False) -> Any:
    """The node at the dotted ``path`` of a plain config tree ("" the root); missing nodes are
    created as empty ones if ``create``, else None."""
    for name in filter(None, path.split(".")):
        if create and not isinstance(tree.get(name), dict):
            tree[name] = {}
        tree = tree.get(name) if isinstance(tree, dict) else None
    return tree


def _upgraded(loaded: DictConfig, command: str | None = None) -> DictConfig:
    """A config stored in an earlier layout (MOVED_KEYS: before the ``tank`` group and the
    per-model fluid configs, 2026-11-27, one flat ``fluid`` node held the grid, walls, inflow and
    every model's keys; validate kept its scenes' tank in ``scenes`` and the judged HydroNet's
    keys at the top level) in today's: each moved key in its new node (where that node does not
    set it already), and a fluid node that held the tank's keys keeps only its own model's (the
    other models' were ignored by the model the file names)."""
    if not isinstance(loaded, DictConfig):
        return loaded
    tree, moved = OmegaConf.to_container(loaded), set()
    for _, source, keys, target, _ in _moves(command):
        node = _node(tree, source)
        found = {k: node.pop(k) for k in keys if k in node} if isinstance(node, dict) else {}
        if found:
            _node(tree, target, create=True).update({k: v for k, v in found.items()
                                                     if k not in _node(tree, target)})
            moved.add(source)
    if not moved:
        return loaded
    if "fluid" in moved:
        fluid = tree["fluid"]
        own = {f.name for f in dataclasses.fields(FLUID_MODELS.get(fluid.get("model", "numerical"), NumericalConfig))}
        tree["fluid"] = {k: v for k, v in fluid.items() if k in own}
    return OmegaConf.create(tree)


def to_dataclass(command: str, raw: Any) -> Any:
    """Merge a composed config into the command's schema, build the dataclasses, validate. The
    ``fluid`` node's schema is that of its ``model`` (``FLUID_MODELS``)."""
    schema = OmegaConf.structured(ROOTS[command])
    if "fluid" in schema:
        model = OmegaConf.select(raw, "fluid.model", default=schema.fluid.model)
        if model not in FLUID_MODELS:
            raise ConfigError(f"config error: fluid.model must be one of {tuple(FLUID_MODELS)} (got '{model}')")
        schema.fluid = OmegaConf.structured(FLUID_MODELS[model])
    _writable(schema)
    for path in _dict_fields(ROOTS[command]):    # the composed dict is the whole dict: a key deleted
        node = OmegaConf.select(schema, path)    # with ~ must not come back from the schema's defaults
        if isinstance(node, DictConfig) and OmegaConf.select(raw, path) is not None:
            node.clear()
    try:
        merged = OmegaConf.merge(schema, raw)
        cfg = OmegaConf.to_object(merged)
    except OmegaConfBaseException as err:
        raise ConfigError(_one_line(err, command)) from None
    cfg.validate()
    return cfg


def _writable(node: DictConfig | ListConfig) -> None:
    """Frozen dataclasses (the modules' own parameter classes) make read-only nodes, tuples
    included; lift that so overrides can be merged in (the dataclass constructors still validate
    the result)."""
    node._set_flag("readonly", False)
    keys = node.keys() if isinstance(node, DictConfig) else range(len(node))
    for key in keys:
        child = node._get_node(key)
        child._set_flag("readonly", False)
        if isinstance(child, (DictConfig, ListConfig)):
            _writable(child)


def to_yaml(cfg: Any) -> str:
    """The resolved config as YAML (stored with every output)."""
    return OmegaConf.to_yaml(OmegaConf.structured(cfg))


def _one_line(err: Exception, command: str | None = None) -> str:
    """Condense an OmegaConf/Hydra error into one line with a hint on how to fix it (for a key
    that ``command`` keeps elsewhere now: where, ``_moved``)."""
    text = " ".join(str(err).split()) or type(err).__name__
    foreign = re.search(r"Key '([^']+)' not in '(\w+Config)' full_key: (fluid\.\S+)", text)
    if foreign and foreign.group(2) in {c.__name__ for c in FLUID_MODELS.values()}:
        model = next(m for m, c in FLUID_MODELS.items() if c.__name__ == foreign.group(2))
        return (f"config error: {foreign.group(3)} is not a setting of fluid={model} (each fluid model has its own "
                f"keys, conf/fluid/{model}.yaml: switch models with the group, fluid={model}, not fluid.model; "
                "the tank's grid, walls and inflow are tank.*)")
    unknown = re.search(r"Could not override '([^']+)'", text) or re.search(r"Key '([^']+)' not in", text)
    added = re.search(r"Key '[^']+' not in '\w+' full_key: (\S+)", text)    # a +key=... or a config file's key
    for key in [m.group(1) for m in (unknown, added) if m]:
        moved = _moved(key, command)
        if moved:
            return f"config error: '{key}' is a setting of {moved[0]}: use {moved[1]}"
    if unknown and ("not in struct" in text or "Could not override" in text):
        key = unknown.group(1)
        return (f"config error: unknown config key '{key}' (check the spelling; "
                "`fishsim <command> --help` lists the config groups and keys)")
    for tail in (" full_key:", " Config search path:", " See https:"):
        text = text.split(tail)[0]
    if text.startswith("Ambiguous value for argument"):       # a sweep without -m
        text = text.split(" 3. To sweep over it")[0] + f"; {NO_SWEEPS}"
    return f"config error: {text.strip()}"
