"""Replayed fish in the training pool: a recorded simulation's surface through the coupling's calls,
its own walls, reset before the record runs out, and refused on another grid."""

import math
from dataclasses import replace

import h5py
import numpy as np
import pytest
import torch
import yaml

from fishsim.coupling import band_boundary, band_margin, surface_band
from fishsim.errors import ConfigError
from fishsim.fluid.hydronet.config import PoolConfig, TrainConfig
from fishsim.learn.pool import Replay, ScenePool, frames_left, replay_track, scene_boundaries

H, W, DX, FRAMES, U = 24, 48, 2.5e-3, 6, 0.05


def _record(path, tank=None, frames=FRAMES, members=2):
    """A minimal trajectory: a disc of radius 1 cm (40 nodes) moving along +x at U (member m at
    height 0.02 + 0.01 m), frames at (k + 1) h, in a closed H x W tank with walls 3 / 4 cells."""
    tank = tank or {"H": H, "W": W, "dx": DX, "wall_y": 3, "wall_x": 4, "inflow": 0.0}
    th = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    t = 0.01 * (np.arange(frames) + 1)
    q = np.zeros((frames, members, 40, 2))
    for m in range(members):
        q[:, m, :, 0] = 0.04 + U * t[:, None] + 0.01 * np.cos(th)
        q[:, m, :, 1] = 0.02 + 0.01 * m + 0.01 * np.sin(th)
    qdot = np.zeros_like(q)
    qdot[..., 0] = U
    cfg = {"tank": tank, "h": 0.01, "coupling": {"sigma": 5e-7}, "hold_x": False, "hold_y": False, "tunnel": False}
    with h5py.File(path, "w") as f:
        f.create_dataset("config", data=yaml.safe_dump(cfg))
        f.create_dataset("metrics/time", data=t)
        f.create_dataset("mesh/surface", data=np.arange(40))
        f.create_dataset("solid/q", data=q)
        f.create_dataset("solid/qdot", data=qdot)
        f.attrs["complete"], f.attrs["n_frames"] = True, frames
    return str(path)


@pytest.fixture
def replay_pool(tmp_path):
    return PoolConfig(size=4, H=H, W=W, dx=DX, episode_steps=8, replay=(_record(tmp_path / "tr.h5"),), p_replay=1.0)


def test_a_replayed_fish_is_the_coupling_boundary_of_its_recorded_frame(replay_pool):
    """ask at step 1 gives, per scene, exactly band_boundary of the recorded nodes of frame 0 (time
    h) united with the record's walls (3 rows, 4 columns), v_d = (U, 0) in the body."""
    pool = ScenePool(replay_pool, batch=2, seed=0)
    idx, _, bd, _ = pool.ask(2)
    grid = replay_pool.grid
    for n, i in enumerate(idx.tolist()):
        (body,) = pool.scenes[i].bodies
        assert isinstance(body, Replay) and pool.scenes[i].wall == (3, 4)
        q = torch.as_tensor(replay_track(body.path, body.member).q[0])[None]
        b, _ = band_boundary(q, torch.zeros_like(q) + torch.tensor([U, 0.0]), surface_band(q, grid, band_margin(5e-7, DX)),
                             grid, sigma=5e-7)
        inside = (slice(5, -5), slice(6, -6))                          # off the wall bands
        assert torch.allclose(bd.mask[n, 0][inside], b[0, 0][inside], atol=1e-6)
        assert bd.mask[n, 0, :3].min() == 1 and bd.mask[n, 0, :, :4].min() == 1
        core = b[0, 0] > 0.99
        assert torch.allclose(bd.velocity[n, 0][core], torch.tensor(U)) and bd.velocity[n, 1][core].abs().max() < 1e-6


def test_replays_reset_before_their_record_runs_out(replay_pool):
    """Unrolled asks of 3 steps play a 6-frame record to its end and never past it: each scene's
    remaining frames stay >= 0, and every scene restarts from rest (t = h) on every other ask."""
    pool = ScenePool(replay_pool, batch=4, seed=1)
    restarts = 0
    for _ in range(6):
        idx, state, _, _ = pool.ask(4, steps=3)
        restarts += sum(math.isclose(pool.scenes[i].t, 0.01) for i in idx.tolist())
        for _ in range(2):
            pool.advance(idx)
        assert all(frames_left(pool.scenes[i], replay_pool) >= 0 for i in idx.tolist())
        pool.tell(idx, state)
    assert restarts == 12                 # a 6-frame record holds two 3-step asks: each scene restarts every other


def test_a_record_from_another_grid_or_a_moving_tank_is_refused(tmp_path, replay_pool):
    other = _record(tmp_path / "big.h5", tank={"H": 2 * H, "W": W, "dx": DX, "wall_y": 3, "wall_x": 4, "inflow": 0.0})
    with pytest.raises(ConfigError, match="pool.H"):
        ScenePool(replace(replay_pool, replay=(other,)), batch=2)
    inflow = _record(tmp_path / "in.h5", tank={"H": H, "W": W, "dx": DX, "wall_y": 3, "wall_x": 4, "inflow": 0.1})
    with pytest.raises(ConfigError, match="moving tank"):
        ScenePool(replace(replay_pool, replay=(inflow,)), batch=2)


def test_replay_settings_are_checked(tmp_path):
    with pytest.raises(ConfigError, match="p_replay"):
        TrainConfig(pool=PoolConfig(p_replay=0.5)).validate()
    with pytest.raises(ConfigError, match="no such trajectory"):
        TrainConfig(pool=PoolConfig(p_replay=0.5, replay=(str(tmp_path / "none.h5"),))).validate()


def test_a_mixed_pool_draws_both_kinds(replay_pool):
    """p_replay = 0.5: replayed fish and random scenes (on the record's grid) side by side, and
    scene_boundaries batches the two kinds of fish (different node counts) together."""
    pool = ScenePool(replace(replay_pool, size=24, p_replay=0.5), batch=4, seed=3)
    kinds = [isinstance(s.bodies[0], Replay) if s.bodies else False for s in pool.scenes]
    assert 4 <= sum(kinds) <= 20
    bd = scene_boundaries(pool.scenes, replay_pool.grid)
    assert bd.mask.shape == (24, 1, H, W) and torch.isfinite(bd.velocity).all()


def test_a_replayed_fish_on_the_teachers_refined_grid(replay_pool):
    """scene_boundaries at refinement 2 (the r = 2 teacher's cells): the record's walls twice as many
    cells thick, the disc's area (sum of b dx^2 off the walls) within 3 % of the pool grid's."""
    from fishsim.fields import Grid

    pool = ScenePool(replay_pool, batch=2, seed=0)
    idx, _, coarse, _ = pool.ask(2)
    fine = scene_boundaries([pool.scenes[i] for i in idx.tolist()], Grid(2 * H, 2 * W, DX / 2), refinement=2)
    assert fine.mask[:, 0, :6].min() == 1 and fine.mask[:, 0, :, :8].min() == 1
    area_coarse = coarse.mask[:, 0, 4:-4, 5:-5].sum((1, 2)) * DX**2
    area_fine = fine.mask[:, 0, 8:-8, 10:-10].sum((1, 2)) * (DX / 2) ** 2
    assert torch.allclose(area_fine, area_coarse, rtol=0.03)
    assert torch.allclose(area_fine, torch.full_like(area_fine, math.pi * 0.01**2), rtol=0.05)
