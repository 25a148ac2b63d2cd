"""The training pool: randomised scenes whose fluid states are HydroNet's own outputs fed back.

Each scene is a tank (no-slip wall bands, optionally an inflow/outflow channel) with moving
bodies, described by plain frozen dataclasses and advanced analytically:

* ``Rigid`` obstacles: box, cylinder or ellipse, static, translating, rotating or both, moving
  smoothly inside the tank (``Motion``: each coordinate oscillates with a random, slowly varying
  rate, so accelerations are continuous and nothing bounces); positions are continuous; the
  soft mask comes from the continuous signed distance s: b = sigmoid(sign(s) s^2 / sigma), the
  coupling's form (``fishsim.coupling.mask``) with d = s^2; v_d = the rigid velocity field, not
  multiplied by b (the ``Boundary`` contract, exactly what the coupling hands the fluid).
* ``Fish``: our fish mesh's surface polyline (``fishsim.mesh.make_fish_mesh``), scaled to a random
  length, bent by the travelling wave (paper App. B envelope, X = 0 at the tail)

      h(X, t) = A(X) sin(gamma X + omega t + phi) (1 - exp(-t / t_a)),  A(X) = A_tail v(X) / v(0),
      v(X) = 4/(25 L) X^2 - 6/25 X + L/10,

  applied laterally to the surface nodes, optionally translating; mask and v_d come from the
  coupling itself (``soft_mask`` / ``boundary_velocity``), exactly as in the coupled simulation.
* ``Replay``: a fish of a coupled simulation (a ``fishsim simulate`` trajectory on the training
  grid itself, ``pool.replay``) played back from its first frame, the fluid at rest as the
  simulation's was: its recorded surface nodes and velocities through the same coupling calls,
  in the simulation's tank (its walls). These are the swimming task's own boundaries: the PD
  fish's shapes, recoil and forward speed, which the prescribed ``Fish`` only imitates. A scene
  whose recording is about to run out is reset (``ScenePool.ask``).

Bodies are merged with the walls by ``fishsim.fluid.grid.union``. All speeds stay below
``max_speed`` (0.5 m/s: the paper's tail speed). New scenes start at rest (a = p = 0); one scene is
reset every ``reset_every`` ``tell`` calls, round robin (Wandel et al.), so a scene lives for about
``episode_steps`` of its own steps. With conditioning, each scene draws its own (rho, mu).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import cache, lru_cache

import numpy as np
import torch
from torch import Tensor

from fishsim.coupling import band_boundary, band_margin, surface_band
from fishsim.fields import Boundary, FluidParams, FluidState, Grid
from fishsim.fluid.grid import channel, curl, union
from fishsim.fluid.hydronet.config import PoolConfig

SIGMA_COUPLING = 5e-7  # m^2, the coupling's default mask softness
RUNAWAY = 4.0          # a stored state faster than RUNAWAY * max_speed has diverged: its scene is reset


# ------------------------------------------------------------------------------------ scenes


@dataclass(frozen=True)
class Motion:
    """Smooth bounded planar motion. Each coordinate oscillates inside the allowed box,

        x_k = c_k + R_k sin(phi_k),  v_k = R_k cos(phi_k) w_k,   k = x, y

    with the phase rate w_k (rad/s) relaxing (0.1 s) towards an Ornstein-Uhlenbeck target, so the
    body never leaves the tank and its acceleration stays continuous and bounded (no bounces).
    The heading theta turns at omega, relaxing towards an OU target of mean ``spin``.

    centre, radius: c_k, R_k of the allowed box (m); phase, rate, rate_target: phi_k, w_k and its
    target; theta (rad), omega, omega_target (rad/s); speed: typical translation speed (m/s);
    spin, spin_std: mean and std of the target omega; extent: bounding half-extents (m).
    """

    centre: tuple[float, float]
    radius: tuple[float, float]
    phase: tuple[float, float]
    rate: tuple[float, float]
    rate_target: tuple[float, float]
    theta: float
    omega: float
    omega_target: float
    speed: float
    spin: float
    spin_std: float
    extent: tuple[float, float]

    @property
    def pose(self) -> tuple[float, float, float]:
        """(x, y, theta) in m, m, rad."""
        c, r, ph = self.centre, self.radius, self.phase
        return c[0] + r[0] * math.sin(ph[0]), c[1] + r[1] * math.sin(ph[1]), self.theta

    @property
    def vel(self) -> tuple[float, float, float]:
        """(vx, vy, omega) in m/s, m/s, rad/s."""
        r, ph, w = self.radius, self.phase, self.rate
        return r[0] * math.cos(ph[0]) * w[0], r[1] * math.cos(ph[1]) * w[1], self.omega


@dataclass(frozen=True)
class Rigid:
    """A rigid obstacle: shape "box" | "cylinder" | "ellipse", half-sizes (m) in its own frame."""

    shape: str
    half: tuple[float, float]
    motion: Motion


@dataclass(frozen=True)
class Fish:
    """A swimming fish: length L (m), tail amplitude A_tail (m), frequency (Hz), wave number gamma
    (rad/m), phase phi, activation ramp t_a (s); ``motion`` translates it (no turning)."""

    length: float
    amp: float
    freq: float
    wave: float
    phase: float
    ramp: float
    motion: Motion


@dataclass(frozen=True)
class Replay:
    """Member ``member`` of the trajectory file ``path`` (``replay_track``), played back."""

    path: str
    member: int


@dataclass(frozen=True)
class Track:
    """A recorded fish: surface nodes q and velocities qdot [T, S, 2] (m, m/s) at times
    (k + 1) h, k = 0..T-1 (a trajectory's frames), on a tank of H x W cells of dx (m) with walls
    (rows, cols) cells thick, mask softness sigma (m^2); ``moving``: the fish was held or the tank
    moved (tunnel, inflow)."""

    q: np.ndarray
    qdot: np.ndarray
    h: float
    H: int
    W: int
    dx: float
    wall: tuple[int, int]
    sigma: float
    moving: bool = False

    @property
    def frames(self) -> int:
        return len(self.q)


@dataclass(frozen=True)
class Scene:
    """One training scene at time t (s): wall thickness (rows, cols) in cells, inflow speed (m/s)
    reached with time constant ``inflow_ramp`` (s), bodies, mask softness sigma (m^2), fluid."""

    t: float
    wall: tuple[int, int]
    inflow: float
    inflow_ramp: float
    bodies: tuple = field(default_factory=tuple)
    sigma: float = SIGMA_COUPLING
    rho: float = 50.0
    mu: float = 1.25e-4


# ------------------------------------------------------------------------ random generation


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _place(rng: np.random.Generator, cfg: PoolConfig, wall: tuple[int, int], extent, speed, spin,
           spin_std, theta) -> Motion:
    """A Motion at rest at a uniform random position where the body fits inside the walls."""
    lo, hi = _centre_bounds(cfg, wall, extent)
    centre = tuple(0.5 * (lo[k] + hi[k]) for k in (0, 1))
    radius = tuple(max(0.5 * (hi[k] - lo[k]), 0.0) for k in (0, 1))
    phase = tuple(float(np.arcsin(rng.uniform(-1, 1))) for _ in (0, 1))
    target = tuple(float(rng.normal(0, _rate_std(speed, r))) for r in radius)
    return Motion(centre, radius, phase, (0.0, 0.0), target, theta, 0.0, spin, speed, spin, spin_std, extent)


def _rate_std(speed: float, radius: float) -> float:
    """Phase-rate std (rad/s) giving translation speeds ~ ``speed`` over an amplitude ``radius``."""
    return speed / radius if radius > 1e-9 and speed > 0 else 0.0


def _centre_bounds(cfg: PoolConfig, wall: tuple[int, int], extent) -> tuple[tuple, tuple]:
    """Allowed centre box ((x_lo, y_lo), (x_hi, y_hi)): walls + extent + 2 cells of clearance."""
    gap_x, gap_y = (wall[1] + 2) * cfg.dx + extent[0], (wall[0] + 2) * cfg.dx + extent[1]
    return (gap_x, gap_y), (cfg.W * cfg.dx - gap_x, cfg.H * cfg.dx - gap_y)


def random_rigid(rng: np.random.Generator, cfg: PoolConfig, wall: tuple[int, int]) -> Rigid:
    """A box, cylinder or ellipse; static, translating, rotating or both (equal odds)."""
    shape = str(rng.choice(["box", "cylinder", "ellipse"]))
    r = rng.uniform(*cfg.obstacle_cells, size=2) * cfg.dx
    half = (float(r[0]), float(r[0])) if shape == "cylinder" else (float(r[0]), float(r[1]))
    radius = math.hypot(*half) if shape == "box" else max(half)
    mode = int(rng.integers(4))  # 0 static, 1 translating, 2 rotating, 3 both
    speed = float(rng.uniform(0.02, 0.25)) if mode in (1, 3) else 0.0
    surface = rng.uniform(0.05, cfg.max_speed) * rng.choice([-1.0, 1.0])
    spin = float(surface / radius) if mode in (2, 3) else 0.0
    theta = float(rng.uniform(0, 2 * math.pi))
    return Rigid(shape, half, _place(rng, cfg, wall, (radius, radius), speed, spin, 0.2 * abs(spin), theta))


def random_fish(rng: np.random.Generator, cfg: PoolConfig, wall: tuple[int, int]) -> Fish:
    """A fish with random size, frequency, amplitude (tail speed <= max_speed), heading ~ 0 or pi."""
    L = float(rng.uniform(*cfg.fish_length))
    freq = float(rng.uniform(*cfg.fish_freq))
    amp = min(float(rng.uniform(*cfg.fish_amp)) * L, 0.9 * cfg.max_speed / (2 * math.pi * freq))
    wave = 2 * math.pi / (L * float(rng.uniform(*cfg.fish_wavelength)))
    theta = float(rng.choice([0.0, math.pi]) + rng.normal(0.0, 0.25))
    half_w = 0.04 * L + amp
    c, s = abs(math.cos(theta)), abs(math.sin(theta))
    extent = (c * L / 2 + s * half_w, s * L / 2 + c * half_w)
    speed = float(rng.uniform(*cfg.fish_speed)) if rng.random() < 0.5 else 0.0
    motion = _place(rng, cfg, wall, extent, speed, 0.0, 0.0, theta)
    return Fish(L, amp, freq, wave, float(rng.uniform(0, 2 * math.pi)), float(rng.uniform(0.0, 0.3)), motion)


def random_scene(rng: np.random.Generator, cfg: PoolConfig) -> Scene:
    """A new scene at t = 0: walls, maybe an inflow, a fish and/or rigid obstacles, a fluid; or,
    with probability ``p_replay``, a recorded fish in its own tank (``replay_scene``)."""
    if cfg.p_replay > 0 and rng.random() < cfg.p_replay:
        return replay_scene(rng, cfg)
    wall = (int(rng.integers(cfg.wall[0], cfg.wall[1] + 1)), int(rng.integers(cfg.wall[0], cfg.wall[1] + 1)))
    inflow = 0.0
    if rng.random() < cfg.p_inflow:
        inflow = float(rng.uniform(0.05, cfg.max_speed) * rng.choice([-1.0, 1.0]))
    bodies: list = []
    if rng.random() < cfg.p_fish:
        bodies.append(random_fish(rng, cfg, wall))
        n_obst = int(rng.random() < 0.3) if cfg.max_obstacles else 0
    else:
        n_obst = int(rng.integers(0 if inflow else 1, cfg.max_obstacles + 1))
    bodies += [random_rigid(rng, cfg, wall) for _ in range(n_obst)]
    sigma = SIGMA_COUPLING if rng.random() < cfg.p_sigma_coupling else _log_uniform(rng, *cfg.sigma)
    rho = float(rng.uniform(*cfg.rho))
    mu = _log_uniform(rng, *cfg.mu) if cfg.mu[1] > cfg.mu[0] else cfg.mu[0]
    return Scene(0.0, wall, inflow, float(rng.uniform(0.0, 0.5)), tuple(bodies), sigma, rho, mu)


def replay_scene(rng: np.random.Generator, cfg: PoolConfig) -> Scene:
    """A recorded fish drawn uniformly from every member of the ``cfg.replay`` files, at its
    first frame, in its simulation's tank and mask softness; the fluid's (rho, mu) drawn as
    for any scene."""
    sources = replay_sources(cfg)
    path, member = sources[int(rng.integers(len(sources)))]
    track = replay_track(path, member)
    check_replay(path, track, cfg.grid, cfg.h)
    rho = float(rng.uniform(*cfg.rho))
    mu = _log_uniform(rng, *cfg.mu) if cfg.mu[1] > cfg.mu[0] else cfg.mu[0]
    return Scene(0.0, track.wall, 0.0, 0.0, (Replay(path, member),), track.sigma, rho, mu)


def replay_sources(cfg: PoolConfig) -> list[tuple[str, int]]:
    """(path, member) of every fish in the ``cfg.replay`` trajectory files."""
    return [(path, m) for path in cfg.replay for m in range(_members(path))]


@cache
def _members(path: str) -> int:
    from fishsim.io.trajectory import read_trajectory

    with read_trajectory(path, load_fluid=False, lazy=True) as tr:
        return int(tr["solid/q"].shape[1])


@lru_cache(maxsize=64)
def replay_track(path: str, member: int) -> Track:
    """Member ``member`` of a ``fishsim simulate`` trajectory as a ``Track``: its surface nodes
    (the mesh's surface polyline) over the flushed frames."""
    import yaml

    from fishsim.io.trajectory import read_trajectory

    with read_trajectory(path, load_fluid=False, lazy=True) as tr:
        cfg = yaml.safe_load(tr.config_yaml)
        tank, T = cfg["tank"], tr.n_frames
        surface = np.asarray(tr["mesh/surface"])
        q = np.asarray(tr["solid/q"][:T, member])[:, surface]
        qdot = np.asarray(tr["solid/qdot"][:T, member])[:, surface]
    moving = bool(cfg.get("hold_x") or cfg.get("hold_y") or cfg.get("tunnel") or tank.get("inflow", 0.0))
    return Track(q.astype(np.float32), qdot.astype(np.float32), float(cfg["h"]), int(tank["H"]), int(tank["W"]),
                 float(tank["dx"]), (int(tank["wall_y"]), int(tank["wall_x"])), float(cfg["coupling"]["sigma"]),
                 moving)


def check_replay(path: str, track: Track, grid: Grid, h: float) -> None:
    """ConfigError unless the recorded simulation ran on ``grid`` with frames of ``h`` seconds in
    a fixed tank (not held, no tunnel, no inflow) for at least 2 frames: else its fish would not
    be where the training grid's walls and fluid put it."""
    from fishsim.errors import ConfigError

    same_grid = (track.H, track.W) == (grid.H, grid.W) and math.isclose(track.dx, grid.dx)
    if not (same_grid and math.isclose(track.h, h) and not track.moving and track.frames >= 2):
        raise ConfigError(
            f"pool.replay: {path} ran on {track.H} x {track.W} cells of {track.dx} m, h = {track.h} s, "
            f"{track.frames} frames{', a held fish or a moving tank' if track.moving else ''}; a replayed fish needs "
            f"the pool's grid ({grid.H} x {grid.W} of {grid.dx} m: pool.H, pool.W, pool.dx), its h (pool.h), a "
            "fixed tank and at least 2 frames: simulate it so, or set pool.H/W/dx to its tank")


def replay_frame(track: Track, t: float) -> int:
    """The recorded frame at scene time t: frame k holds time (k + 1) h (clamped to the record)."""
    return min(max(round(t / track.h) - 1, 0), track.frames - 1)


def frames_left(scene: Scene, cfg: PoolConfig) -> float:
    """Steps of h the scene can still advance before a replayed fish runs out (inf without one):
    at time t the record has given frames up to t / h - 1 of its T."""
    left = [replay_track(b.path, b.member).frames - round(scene.t / cfg.h)
            for b in scene.bodies if isinstance(b, Replay)]
    return min(left, default=math.inf)


# --------------------------------------------------------------------------------- motion


def ou_step(v: float, mean: float, std: float, tau: float, h: float, rng: np.random.Generator) -> float:
    """Ornstein-Uhlenbeck step: v <- mean + c (v - mean) + std sqrt(1 - c^2) xi, c = exp(-h / tau)."""
    c = math.exp(-h / tau)
    return mean + c * (v - mean) + std * math.sqrt(1 - c * c) * float(rng.normal())


MAX_RATE = 4 * math.pi  # rad/s: at most 2 oscillations per second across the tank


def advance_motion(m: Motion, cfg: PoolConfig, wall, rng: np.random.Generator) -> Motion:
    """One step h of the smooth random motion (``Motion``):

        target <- OU(target)                      (correlation time tau_motion)
        w <- w + (target - w) h / tau_v           (tau_v = 0.1 s: continuous acceleration)
        phi <- phi + h (w_old + w_new) / 2        (trapezoidal), theta likewise with omega

    |w_k|, |target_k| <= min(max_speed / (sqrt(2) R_k), 4 pi): the speed never exceeds max_speed
    and one step changes it by at most 0.2 max_speed / sqrt(2) + R w^2 h (typically < 1 cm/s).
    """
    h, tau, tau_v = cfg.h, cfg.tau_motion, 0.1
    phase, rate, target = [], [], []
    for k in (0, 1):
        std = _rate_std(m.speed, m.radius[k])
        cap = min(cfg.max_speed / (math.sqrt(2) * m.radius[k]), MAX_RATE) if m.radius[k] > 0 else 0.0
        t = ou_step(m.rate_target[k], 0.0, std, tau, h, rng) if std > 0 else 0.0
        t = min(max(t, -cap), cap)
        w = min(max(m.rate[k] + (t - m.rate[k]) * h / tau_v, -cap), cap)
        phase.append(m.phase[k] + 0.5 * h * (m.rate[k] + w))
        rate.append(w)
        target.append(t)
    om_t = ou_step(m.omega_target, m.spin, m.spin_std, tau, h, rng) if m.spin_std > 0 else m.omega_target
    om = m.omega + (om_t - m.omega) * h / tau_v
    return replace(m, phase=tuple(phase), rate=tuple(rate), rate_target=tuple(target),
                   theta=m.theta + 0.5 * h * (m.omega + om), omega=om, omega_target=om_t)


def advance(scene: Scene, cfg: PoolConfig, rng: np.random.Generator) -> Scene:
    """The scene one step h later (bodies moved, t + h); the input is not modified."""
    bodies = tuple(b if isinstance(b, Replay) else replace(b, motion=advance_motion(b.motion, cfg, scene.wall, rng))
                   for b in scene.bodies)
    return replace(scene, t=scene.t + cfg.h, bodies=bodies)


# ------------------------------------------------------------------------------ boundaries


def mask_from_distance(s: Tensor, sigma: float) -> Tensor:
    """Soft mask b = sigmoid(sign(s) s^2 / sigma) from a signed distance s (m, > 0 inside)."""
    return torch.sigmoid(torch.sign(s) * s * s / sigma)


def rigid_distance(body: Rigid, x: Tensor) -> Tensor:
    """Signed distance (m, positive inside) of cell centres x [H, W, 2] to the body (boxes exact,
    ellipses to first order: s = -k0 (k0 - 1) / k1, k0 = |l / r|, k1 = |l / r^2|)."""
    cx, cy, th = body.motion.pose
    dx, dy = x[..., 0] - cx, x[..., 1] - cy
    lx, ly = math.cos(th) * dx + math.sin(th) * dy, -math.sin(th) * dx + math.cos(th) * dy
    a, b = body.half
    if body.shape == "cylinder":
        return a - torch.sqrt(lx * lx + ly * ly)
    if body.shape == "box":
        qx, qy = lx.abs() - a, ly.abs() - b
        outside = torch.sqrt(qx.clamp_min(0) ** 2 + qy.clamp_min(0) ** 2)
        return -(outside + torch.maximum(qx, qy).clamp_max(0))
    k0 = torch.sqrt((lx / a) ** 2 + (ly / b) ** 2)
    k1 = torch.sqrt((lx / a**2) ** 2 + (ly / b**2) ** 2).clamp_min(1e-12)
    return -k0 * (k0 - 1) / k1


def rigid_boundary(body: Rigid, x: Tensor, sigma: float) -> Boundary:
    """b [1,1,H,W] and the body's own velocity field v_d = v + omega x (x - c) [1,2,H,W] (the
    ``Boundary`` contract: not multiplied by b, exactly what the coupling hands the fluid)."""
    b = mask_from_distance(rigid_distance(body, x), sigma)
    (cx, cy, _), (vx, vy, om) = body.motion.pose, body.motion.vel
    u = torch.stack([vx - om * (x[..., 1] - cy), vy + om * (x[..., 0] - cx)])
    return Boundary(mask=b[None, None], velocity=u[None])


@lru_cache(maxsize=1)
def fish_outline(stride: int = 2) -> np.ndarray:
    """Surface polyline of the default fish mesh in units of its length, [S, 2] (X/L, Y/L), ccw.

    Every ``stride``-th surface node (2: ~4 mm segments, 109 nodes): the mask changes by < 0.2 %
    of its area and the coupling's band search, the pool's main cost, runs ~1.6x faster.
    """
    from fishsim.mesh import make_fish_mesh

    mesh = make_fish_mesh(elements_across=2)  # the uniform mesh the shipped model was trained on
    return mesh.points[mesh.surface[::stride]] / mesh.length


def envelope(X: np.ndarray, L: float) -> np.ndarray:
    """Carangiform envelope v(X) / v(0), v(X) = 4/(25 L) X^2 - 6/25 X + L/10 (X = 0 at the tail)."""
    return (4 / (25 * L) * X**2 - 6 / 25 * X + L / 10) / (L / 10)


def fish_surface(fish: Fish, t: float) -> tuple[np.ndarray, np.ndarray]:
    """World-frame surface nodes q^k and velocities qdot^k of the bent, translating fish, [S, 2].

    Body frame: (X - L/2, Y + h(X, t)); dh/dt from the analytic derivative of the wave and ramp.
    """
    XY = fish_outline() * fish.length
    X, Y = XY[:, 0], XY[:, 1]
    A = fish.amp * envelope(X, fish.length)
    w = 2 * math.pi * fish.freq
    arg = fish.wave * X + w * t + fish.phase
    ramp, dramp = (1.0, 0.0) if fish.ramp <= 0 else (1 - math.exp(-t / fish.ramp), math.exp(-t / fish.ramp) / fish.ramp)
    lat = A * np.sin(arg) * ramp
    dlat = A * (w * np.cos(arg) * ramp + np.sin(arg) * dramp)
    (cx, cy, th), (vx, vy, _) = fish.motion.pose, fish.motion.vel
    c, s = math.cos(th), math.sin(th)
    bx, by = X - fish.length / 2, Y + lat
    q = np.stack([cx + c * bx - s * by, cy + s * bx + c * by], -1)
    qdot = np.stack([vx - s * dlat, vy + c * dlat], -1)
    return q, qdot


def body_surface(body: Fish | Replay, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Surface nodes q^k and velocities qdot^k [S, 2] of a prescribed or a replayed fish at t."""
    if isinstance(body, Fish):
        return fish_surface(body, t)
    track = replay_track(body.path, body.member)
    k = replay_frame(track, t)
    return track.q[k], track.qdot[k]


def fish_boundaries(fish: list[Fish | Replay], times: list[float], sigma: list[float], grid: Grid,
                    device) -> list[Boundary]:
    """The coupling's soft masks and boundary velocities of several fish, [1,1|2,H,W] each.

    Fish sharing a softness sigma and a surface node count are batched through one
    ``surface_band`` call.
    """
    out: list = [None] * len(fish)
    surfaces = [body_surface(f, t) for f, t in zip(fish, times)]
    groups = [(sig, len(z[0])) for sig, z in zip(sigma, surfaces)]
    for group in sorted(set(groups)):
        sig = group[0]
        ids = [k for k, g in enumerate(groups) if g == group]
        qq = [surfaces[k] for k in ids]
        q = torch.as_tensor(np.stack([z[0] for z in qq]), dtype=torch.float32, device=device)
        qdot = torch.as_tensor(np.stack([z[1] for z in qq]), dtype=torch.float32, device=device)
        band = surface_band(q, grid, band_margin(sig, grid.dx))
        b, v = band_boundary(q, qdot, band, grid, sigma=sig)                  # as the coupling does
        for n, k in enumerate(ids):
            out[k] = Boundary(mask=b[n : n + 1], velocity=v[n : n + 1])
    return out


def inflow_speed(scene: Scene) -> float:
    """Channel inflow at time t: U (1 - exp(-t / t_ramp)) (impulsive for t_ramp = 0), m/s."""
    if scene.inflow_ramp <= 0:
        return scene.inflow
    return scene.inflow * (1 - math.exp(-scene.t / scene.inflow_ramp))


def scene_boundaries(scenes: list[Scene], grid: Grid, device=None, refinement: int = 1) -> Boundary:
    """Walls (+ inflow) united with every body, for each scene at its own time:
    b [B,1,H,W], v_d [B,2,H,W] on ``grid``, the pool's grid or one ``refinement`` times finer
    (the walls' thickness, counted in pool cells, scaled to its cells)."""
    x = grid.cell_centres(device=device)
    fish = [(n, b) for n, s in enumerate(scenes) for b in s.bodies if isinstance(b, (Fish, Replay))]
    fish_bd = fish_boundaries([f for _, f in fish], [scenes[n].t for n, _ in fish],
                              [scenes[n].sigma for n, _ in fish], grid, device)
    parts = []
    for n, scene in enumerate(scenes):
        out = channel(grid, inflow_speed(scene), refinement * scene.wall[0], refinement * scene.wall[1], 1, device)
        for body in scene.bodies:
            if isinstance(body, Rigid):
                out = union(out, rigid_boundary(body, x, scene.sigma))
        for (m, _), bd in zip(fish, fish_bd):
            if m == n:
                out = union(out, bd)
        parts.append(out)
    return Boundary(torch.cat([b.mask for b in parts]), torch.cat([b.velocity for b in parts]))


def max_speeds(a: Tensor, dx: float) -> Tensor:
    """max |v| [B] (m/s) over the faces of each sample's v = curl a (NaN where a is not finite)."""
    return torch.stack([c.abs().flatten(1).amax(1) for c in curl(a, dx)]).amax(0)


# ------------------------------------------------------------------------------------ pool


class ScenePool:
    """``size`` scenes and their fluid states; ``ask`` a batch, step it, ``tell`` the result.

    States live on ``device``: a [N,1,H+1,W+1] (m^2/s), p [N,1,H,W] (Pa). All randomness comes
    from one numpy Generator (``seed``), saved by ``state_dict`` for exact resumption.
    """

    def __init__(self, cfg: PoolConfig, batch: int, seed: int = 0, device="cpu"):
        self.cfg, self.grid, self.device = cfg, cfg.grid, torch.device(device)
        self.reset_every = max(1, round(cfg.episode_steps / batch))
        self.rng = np.random.default_rng(seed)
        self.scenes = [random_scene(self.rng, cfg) for _ in range(cfg.size)]
        g = self.grid
        self.a = torch.zeros(cfg.size, 1, g.H + 1, g.W + 1, device=self.device, dtype=torch.float32)
        self.p = torch.zeros(cfg.size, 1, g.H, g.W, device=self.device, dtype=torch.float32)
        self.told, self.next_reset = 0, 0

    def ask(self, batch: int, steps: int = 1) -> tuple[Tensor, FluidState, Boundary, FluidParams]:
        """Draw ``batch`` distinct scenes, advance them by h and return (indices [B], state at t,
        boundary at t + h, params): the inputs of one training step. A scene whose replayed fish
        cannot advance ``steps`` more frames (the step and an unrolled step's ``advance`` calls)
        is reset first."""
        idx = np.sort(self.rng.choice(self.cfg.size, batch, replace=False))
        for i in idx:
            if frames_left(self.scenes[i], self.cfg) < steps:
                self.reset(i)
            self.scenes[i] = advance(self.scenes[i], self.cfg, self.rng)
        return self._batch(idx)

    def advance(self, idx: Tensor) -> Boundary:
        """Advance the scenes ``idx`` (from ``ask``) by another h; their boundary at that time
        (for a training step unrolled over several steps)."""
        ids = idx.tolist()
        for i in ids:
            self.scenes[i] = advance(self.scenes[i], self.cfg, self.rng)
        return scene_boundaries([self.scenes[i] for i in ids], self.grid, self.device)

    def _batch(self, idx: np.ndarray) -> tuple[Tensor, FluidState, Boundary, FluidParams]:
        scenes = [self.scenes[i] for i in idx]
        boundary = scene_boundaries(scenes, self.grid, self.device)
        params = FluidParams(
            rho=torch.tensor([s.rho for s in scenes], device=self.device, dtype=torch.float32),
            mu=torch.tensor([s.mu for s in scenes], device=self.device, dtype=torch.float32),
            h=self.cfg.h,
        )
        ti = torch.as_tensor(idx, device=self.device)
        return ti, FluidState(self.a[ti], self.p[ti]), boundary, params

    def tell(self, idx: Tensor, state: FluidState) -> None:
        """Store the new states (``_store``) and, every ``reset_every`` calls, reset the next
        scene in round-robin order."""
        self._store(idx, state)
        self.told += 1
        if self.told % self.reset_every == 0:
            self.reset(self.next_reset)
            self.next_reset = (self.next_reset + 1) % self.cfg.size

    def warm(self, step, max_age: int, batch: int) -> None:
        """Age a freshly drawn pool before trained weights train on it: scene i is stepped k_i
        times (k_i uniform in 0..max_age) by ``step`` ((state, boundary at t + h, params) ->
        FluidState, the network), ``batch`` scenes at a time. A pool drawn at once holds only
        start-ups from rest, which a running pool (one reset every ``reset_every`` calls) hardly
        does; training on them first pulled a resumed network away from the developed flows it
        had learned (the frequency study 14-20 % off after 165 iterations, 6 % before; with a
        pool warmed 0..200 steps, 6 %)."""
        ages = self.rng.integers(0, max_age + 1, self.cfg.size)
        for t in range(1, max_age + 1):
            live = np.flatnonzero(ages >= t)
            for chunk in np.array_split(live, -(-len(live) // batch)) if len(live) else ():
                for i in chunk:
                    if frames_left(self.scenes[i], self.cfg) < 1:     # a replay's end: from rest again
                        self.reset(i)
                    self.scenes[i] = advance(self.scenes[i], self.cfg, self.rng)
                idx, state, boundary, params = self._batch(chunk)
                ages[self._store(idx, step(state, boundary, params))] = 0

    def _store(self, idx: Tensor, state: FluidState) -> list[int]:
        """Store the scenes' new states (detached); reset the diverged ones, returned: non-finite,
        or max |v| above ``RUNAWAY`` max_speed (a network rolled out on scenes beyond what it
        learned can run away, and the teacher cannot step such a state: 94 m/s would need 754
        sub-steps)."""
        a, p = state.a.detach().to(self.device, torch.float32), state.p.detach().to(self.device, torch.float32)
        self.a[idx], self.p[idx] = a, p
        speed = max_speeds(a, self.grid.dx)
        sane = (speed <= RUNAWAY * self.cfg.max_speed) & torch.isfinite(p).flatten(1).all(1)   # NaN a: not <=
        bad = idx[~sane].tolist()
        for i in bad:
            self.reset(i)
        return bad

    def reset(self, i: int) -> None:
        """Replace scene i by a new random scene with the fluid at rest."""
        self.scenes[i] = random_scene(self.rng, self.cfg)
        self.a[i], self.p[i] = 0.0, 0.0

    def state_dict(self) -> dict:
        return {"a": self.a.cpu(), "p": self.p.cpu(), "scenes": list(self.scenes),
                "rng": self.rng.bit_generator.state, "told": self.told, "next_reset": self.next_reset}

    def load_state_dict(self, sd: dict) -> None:
        self.a, self.p = sd["a"].to(self.device), sd["p"].to(self.device)
        self.scenes = list(sd["scenes"])
        self.rng.bit_generator.state = sd["rng"]
        self.told, self.next_reset = sd["told"], sd["next_reset"]
