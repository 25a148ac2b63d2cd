"""The scene pool: boundaries, smooth motion, fish kinematics, ask/tell, resets, state_dict."""

import math

import numpy as np
import pytest
import torch

from fishsim.learn.pool import (
    Fish,
    Motion,
    Rigid,
    ScenePool,
    advance,
    advance_motion,
    fish_surface,
    mask_from_distance,
    random_fish,
    random_scene,
    rigid_distance,
    scene_boundaries,
)


def _motion(**kw):
    base = {"centre": (0.06, 0.03), "radius": (0.0, 0.0), "phase": (0.0, 0.0), "rate": (0.0, 0.0),
            "rate_target": (0.0, 0.0), "theta": 0.0, "omega": 0.0, "omega_target": 0.0, "speed": 0.0,
            "spin": 0.0, "spin_std": 0.0, "extent": (0.01, 0.01)}
    return Motion(**{**base, **kw})


def test_boundaries_on_a_refined_grid_hold_the_same_bodies_and_walls(tiny_pool):
    """scene_boundaries on a grid twice as fine (refinement 2): the scenes sampled on cells half as
    wide, the walls as thick in metres, the bodies' area (sum of b, away from the walls) within 5 %
    of the pool grid's."""
    from fishsim.fields import Grid

    pool = ScenePool(tiny_pool, batch=4, seed=5)
    idx, _, coarse, _ = pool.ask(4)
    fine = scene_boundaries([pool.scenes[i] for i in idx.tolist()],
                            Grid(2 * tiny_pool.H, 2 * tiny_pool.W, tiny_pool.dx / 2), refinement=2)
    assert fine.mask.shape[-2:] == (2 * tiny_pool.H, 2 * tiny_pool.W)
    for n, i in enumerate(idx.tolist()):
        rows, cols = pool.scenes[i].wall
        assert fine.mask[n, 0, : 2 * rows].min() == 1 and fine.mask[n, 0, 2 * rows, 2 * cols:-2 * cols].max() < 1
    interior = (slice(None), 0, slice(6, -6), slice(6, -6))         # away from every wall band
    area = coarse.mask.new_tensor([1.0, 0.25]) * torch.stack(
        [coarse.mask[interior].sum((1, 2)), fine.mask[(slice(None), 0, slice(12, -12), slice(12, -12))].sum((1, 2))], 1)
    assert torch.allclose(area[:, 1], area[:, 0], rtol=0.05, atol=0.5)


def test_ask_shapes_and_ranges(tiny_pool):
    """ask: B distinct scenes, soft masks in [0, 1] with partial cells, |v_d| <= max_speed."""
    pool = ScenePool(tiny_pool, batch=4, seed=0)
    idx, state, bd, params = pool.ask(4)
    g = tiny_pool.grid
    assert len(set(idx.tolist())) == 4
    assert state.a.shape == (4, 1, g.H + 1, g.W + 1) and state.p.shape == (4, 1, g.H, g.W)
    assert bd.mask.shape == (4, 1, g.H, g.W) and bd.velocity.shape == (4, 2, g.H, g.W)
    assert bd.mask.min() >= 0 and bd.mask.max() <= 1
    assert bd.velocity.norm(dim=1).max() <= tiny_pool.max_speed * 1.001
    assert torch.equal(bd.mask[:, :, 0, :], torch.ones_like(bd.mask[:, :, 0, :]))  # walls
    assert params.rho.shape == (4,) and params.h == tiny_pool.h


def test_soft_masks_have_partial_cells(tiny_pool):
    """Masks come from continuous distances: cells with 0.05 < b < 0.95 exist around bodies."""
    rng = np.random.default_rng(3)
    scenes = [random_scene(rng, tiny_pool) for _ in range(12)]
    b = scene_boundaries(scenes, tiny_pool.grid).mask
    assert ((b > 0.05) & (b < 0.95)).sum() > 0


def test_ask_tell_round_trip_and_reset(tiny_pool):
    """tell stores the states; every reset_every tells the next scene (round robin) is reset to
    rest at t = 0."""
    pool = ScenePool(tiny_pool, batch=3, seed=1)
    assert pool.reset_every == round(tiny_pool.episode_steps / 3)
    idx, state, _, _ = pool.ask(3)
    new_a = 1e-5 * torch.randn_like(state.a)                # m^2/s: ~4 mm/s on 2.5 mm cells
    new_p = torch.randn_like(state.p)
    pool.tell(idx, type(state)(new_a, new_p))
    assert torch.equal(pool.a[idx], new_a) and torch.equal(pool.p[idx], new_p)
    pool.a.fill_(1.0)
    for _ in range(pool.reset_every - 1):
        pool.tell(idx, type(state)(pool.a[idx], pool.p[idx]))
    assert pool.a[0].abs().sum() == 0 and pool.scenes[0].t == 0.0 and pool.next_reset == 1
    assert pool.a[1:].min() == 1.0


def test_non_finite_states_are_reset(tiny_pool):
    pool = ScenePool(tiny_pool, batch=2, seed=2)
    idx, state, _, _ = pool.ask(2)
    bad = state.a.clone()
    bad[0] = float("nan")
    pool.tell(idx, type(state)(bad, state.p))
    assert torch.isfinite(pool.a).all()


def test_runaway_states_are_reset(tiny_pool):
    """A stored state faster than RUNAWAY max_speed (a diverged network rollout) is reset to rest
    with a new scene; one just below the bound is kept."""
    from fishsim.learn.pool import RUNAWAY

    pool = ScenePool(tiny_pool, batch=2, seed=2)
    idx, state, _, _ = pool.ask(2)
    scenes = [pool.scenes[i] for i in idx.tolist()]
    y = torch.arange(tiny_pool.H + 1, dtype=torch.float32).view(1, 1, -1, 1) * tiny_pool.dx
    a = (y * RUNAWAY * tiny_pool.max_speed * torch.tensor([1.01, 0.99]).view(2, 1, 1, 1)).expand_as(state.a)
    pool.tell(idx, type(state)(a.contiguous(), state.p + 1.0))      # uniform vx = 4.04 / 3.96 max_speed
    i, j = idx.tolist()
    assert pool.a[i].abs().max() == 0 and pool.p[i].abs().max() == 0 and pool.scenes[i] is not scenes[0]
    assert torch.equal(pool.a[j], a[1]) and pool.scenes[j] is scenes[1]


def test_warm_ages_every_scene_by_its_own_count_of_steps(tiny_pool):
    """warm(step, 6, 3): each scene is stepped k_i times (0 <= k_i <= 6, counted here by a step
    that adds 1 to a), its clock advanced by k_i h, with a spread of ages and no round-robin
    reset; a step that returns NaN resets that scene to rest."""
    pool = ScenePool(tiny_pool, batch=3, seed=5)
    sizes = []

    def count(state, boundary, params):
        sizes.append(state.a.shape[0])
        assert boundary.mask.shape[0] == state.a.shape[0] == params.rho.shape[0]
        return type(state)(state.a + 1, state.p)

    pool.warm(count, 6, 3)
    ages = pool.a[:, 0, 0, 0].round().long()
    clocks = torch.tensor([round(s.t / tiny_pool.h) for s in pool.scenes])
    assert torch.equal(ages, clocks) and torch.equal(pool.a, ages.float()[:, None, None, None].expand_as(pool.a))
    assert ages.min() >= 0 and ages.max() <= 6 and len(set(ages.tolist())) >= 3
    assert max(sizes) <= 3 and sum(sizes) == ages.sum() and pool.told == 0
    fresh = ScenePool(tiny_pool, batch=3, seed=5)
    fresh.warm(lambda state, b, p: type(state)(state.a * float("nan"), state.p), 6, 3)
    assert torch.isfinite(fresh.a).all() and fresh.a.abs().max() == 0


def test_state_dict_resumes_identically(tiny_pool):
    """Saving and loading a pool reproduces the next asks exactly (scenes, RNG, states)."""
    pool = ScenePool(tiny_pool, batch=2, seed=4)
    for _ in range(3):
        idx, st, _, _ = pool.ask(2)
        pool.tell(idx, type(st)(st.a + 1e-5, st.p + 1.0))
    sd = pool.state_dict()
    ref = [pool.ask(2) for _ in range(2)]
    other = ScenePool(tiny_pool, batch=2, seed=99)
    other.load_state_dict(sd)
    for r, o in zip(ref, (other.ask(2) for _ in range(2))):
        assert torch.equal(r[0], o[0]) and torch.equal(r[1].a, o[1].a)
        assert torch.equal(r[2].mask, o[2].mask) and torch.equal(r[2].velocity, o[2].velocity)


def test_motion_is_smooth_bounded_and_inside(tiny_pool):
    """Speed <= max_speed, bounded acceleration (|dv| <= h / tau_v (|target| + |v|)), centre
    inside the tank, and the motion really moves."""
    rng = np.random.default_rng(0)
    m = _motion(radius=(0.04, 0.01), speed=0.3, spin=5.0, spin_std=1.0)
    wall = (2, 2)
    vels = []
    for _ in range(400):
        m = advance_motion(m, tiny_pool, wall, rng)
        vels.append(m.vel)
        x, y, _ = m.pose
        assert 0 < x < tiny_pool.W * tiny_pool.dx and 0 < y < tiny_pool.H * tiny_pool.dx
    v = np.array(vels)
    assert np.hypot(v[:, 0], v[:, 1]).max() <= tiny_pool.max_speed + 1e-12
    dv = np.abs(np.diff(v, axis=0))
    assert dv[:, :2].max() < 0.1 and np.median(dv[:, :2]) < 0.01  # m/s per 0.01 s step
    assert np.abs(v[:, :2]).max() > 0.05 and np.abs(v[:, 2]).max() > 1.0


def test_rigid_signed_distances():
    """Exact distances for cylinder and box; mask = 1/2 on the surface, -> 1 inside."""
    x = torch.tensor([[[0.06, 0.03], [0.07, 0.03], [0.06 + 0.02, 0.03 + 0.02]]])  # [1, 3, 2]
    cyl = Rigid("cylinder", (0.01, 0.01), _motion())
    torch.testing.assert_close(rigid_distance(cyl, x)[0], torch.tensor([0.01, 0.0, 0.01 - math.hypot(0.02, 0.02)]))
    box = Rigid("box", (0.01, 0.005), _motion())
    torch.testing.assert_close(rigid_distance(box, x)[0], torch.tensor([0.005, -0.0, -math.hypot(0.01, 0.015)]),
                               atol=1e-7, rtol=0)
    b = mask_from_distance(torch.tensor([0.0, 1e-3, -1e-3]), 5e-7)
    assert b[0] == 0.5 and b[1] > 0.8 and b[2] < 0.2


def test_fish_surface_velocity_is_time_derivative(tiny_pool):
    """qdot of the fish surface equals the central difference of q in time (wave + ramp + drift)."""
    fish = random_fish(np.random.default_rng(5), tiny_pool, (2, 2))
    fish = Fish(fish.length, fish.amp, 4.0, fish.wave, 0.3, 0.2,
                _motion(radius=(0.01, 0.01), phase=(0.0, 0.0), rate=(5.0, -2.0)))
    t, dt = 0.13, 1e-6
    q_plus = fish_surface(fish, t + dt)[0]
    q_minus = fish_surface(fish, t - dt)[0]
    # translation is applied by advance(), not inside fish_surface: add the drift velocity back
    fd = (q_plus - q_minus) / (2 * dt) + np.array([0.05, -0.02])  # R cos(0) w
    np.testing.assert_allclose(fish_surface(fish, t)[1], fd, atol=1e-5)


def test_fish_tail_amplitude_and_speed_cap(tiny_pool):
    """The tail (X = 0) swings with the chosen amplitude; tail speed never exceeds max_speed."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        f = random_fish(rng, tiny_pool, (2, 2))
        assert f.amp * 2 * math.pi * f.freq <= tiny_pool.max_speed
        f = Fish(f.length, f.amp, f.freq, f.wave, f.phase, 0.0, _motion())
        speeds = [np.abs(fish_surface(f, t)[1]).max() for t in np.linspace(0, 1 / f.freq, 20)]
        assert max(speeds) <= tiny_pool.max_speed * 1.02


def test_fish_translation_speed_range(tiny_pool):
    """pool.fish_speed: half the fish translate, each with a typical speed drawn from the range
    (the study's fish swim up to ~0.35 m/s; the default range stops at 0.15)."""
    from dataclasses import replace

    rng = np.random.default_rng(3)
    fast = replace(tiny_pool, fish_speed=(0.3, 0.4))
    speeds = np.array([random_fish(rng, fast, (2, 2)).motion.speed for _ in range(200)])
    moving = speeds[speeds > 0]
    assert 0.3 <= moving.min() and moving.max() <= 0.4
    assert 0.35 < moving.size / speeds.size < 0.65


def test_scene_advances_time_without_mutation(tiny_pool):
    rng = np.random.default_rng(0)
    s = random_scene(rng, tiny_pool)
    s2 = advance(s, tiny_pool, rng)
    assert s.t == 0.0 and s2.t == pytest.approx(tiny_pool.h)


def test_random_fluid_per_scene_for_conditioning(tiny_pool):
    """With fluid ranges, every scene draws rho ~ U[10, 50], mu ~ logU[0.125, 1] mPa s."""
    from dataclasses import replace

    cfg = replace(tiny_pool, size=12, rho=(10.0, 50.0), mu=(1.25e-4, 1e-3))
    _, _, _, params = ScenePool(cfg, batch=12, seed=0).ask(12)
    assert params.rho.min() >= 10 and params.rho.max() <= 50 and params.rho.std() > 1
    assert params.mu.min() >= 1.25e-4 * (1 - 1e-6) and params.mu.max() <= 1e-3 * (1 + 1e-6)
    assert params.mu.max() / params.mu.min() > 1.5


def test_boundary_velocity_follows_the_coupling_contract(tiny_pool):
    """Training boundaries carry the body's own velocity, not b times it (``Boundary`` contract),
    exactly as ``fishsim.coupling.solid_to_fluid`` hands them to the fluid in a simulation: a
    translating cylinder has v_d = U in its soft edge cells too, and the pool's fish equals the
    coupling layer on the same surface."""
    from fishsim.coupling import CouplingConfig, solid_to_fluid
    from fishsim.learn.pool import fish_boundaries, rigid_boundary

    grid = tiny_pool.grid
    body = Rigid("cylinder", (0.01, 0.01), _motion(rate=(3.0, 0.0), radius=(0.01, 0.0), phase=(0.0, 0.0)))
    bd = rigid_boundary(body, grid.cell_centres(), 5e-6)
    edge = (bd.mask > 0.05) & (bd.mask < 0.95)
    assert edge.sum() > 4
    u = body.motion.vel[0]
    assert u > 0.01 and torch.allclose(bd.velocity[:, 0:1][edge], torch.tensor(u, dtype=torch.float32))
    fish = Fish(0.07, 0.004, 4.0, 2 * math.pi / 0.07, 0.3, 0.0, _motion(centre=(0.06, 0.03)))
    (pool_bd,) = fish_boundaries([fish], [0.1], [5e-7], grid, "cpu")
    q, qdot = (torch.as_tensor(z, dtype=torch.float32)[None] for z in fish_surface(fish, 0.1))
    layer = solid_to_fluid(q, qdot, torch.arange(q.shape[1]), grid, CouplingConfig(k_nearest=q.shape[1]))
    torch.testing.assert_close(pool_bd.mask, layer.mask, atol=1e-5, rtol=0)
    torch.testing.assert_close(pool_bd.velocity, layer.velocity, atol=1e-5, rtol=0)
