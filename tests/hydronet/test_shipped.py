"""The shipped HydroNet (fishsim/assets/hydronet.pt): trained, physical, reproducible."""

import json

import numpy as np
import pytest
import torch

from fishsim.fluid.factory import SHIPPED_HYDRONET
from fishsim.fluid.hydronet import HydroNet, HydroNetFluid, PoolConfig, load_hydronet
from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.fluid.numerical import NumericalFluid
from fishsim.learn.evaluate import evaluate
from fishsim.learn.pool import ScenePool
from fishsim.learn.train import export_model


@pytest.fixture(scope="module")
def shipped() -> HydroNet:
    return load_hydronet(SHIPPED_HYDRONET)


def test_metadata_describes_the_model(shipped):
    meta = json.loads(SHIPPED_HYDRONET.with_suffix(".json").read_text())
    assert meta["net"] == {k: getattr(shipped.cfg, k) for k in meta["net"]}
    for key in ("commands", "train_config", "iterations", "wall_time_s", "final_losses", "evaluation"):
        assert key in meta, key
    pool = meta["train_config"]["pool"]           # the range a run is checked against is the one it was trained on
    assert meta["training_range"] == {"rho": pool["rho"], "mu": pool["mu"], "dx": pool["dx"], "h": pool["h"]}
    assert SHIPPED_HYDRONET.stat().st_size < 20e6


def _scene_after_warmup(batch=4, steps=20):
    """Pool scenes at 64 x 128 and the numerical solver's state after ``steps`` steps from rest."""
    cfg = PoolConfig(size=batch, episode_steps=10**6)
    pool = ScenePool(cfg, batch, seed=2024)
    num = NumericalFluid(cfg.grid)
    idx, state, boundary, params = pool.ask(batch)
    for _ in range(steps):
        state = num.step(state, boundary, params)
        pool.tell(idx, state)
        idx, _, boundary, params = pool.ask(batch)
    return cfg.grid, state, boundary, params


def test_trained_model_beats_an_untrained_one_on_the_physics_loss(shipped):
    """Fixed held-out pool scenes rolled out from rest by each network (40 steps): the mean
    log physics loss of the second half. Measured with the shipped model: trained -6.6,
    untrained -2.6 (a 50x smaller residual; the physics-only model shipped before 2026-11-26,
    trained on this loss alone: -7.5)."""
    from fishsim.fluid.hydronet.config import TrainConfig
    from fishsim.learn.train import validate

    cfg = TrainConfig(bf16=False, val_scenes=4, val_steps=40)
    torch.manual_seed(0)
    untrained = HydroNet(shipped.cfg).eval()
    trained_loss, untrained_loss = validate(shipped, cfg), validate(untrained, cfg)
    assert trained_loss < untrained_loss - 3.0, (trained_loss, untrained_loss)  # > 20x smaller residual


def test_towed_cylinder_drag_has_the_right_sign_and_size(shipped):
    """0.2 m/s tow in the paper's tank, 20 steps from a 20-step numerical start: the IBM drag of
    HydroNet opposes the motion and is within a factor 2 of the numerical solver's (measured
    ratio 0.96 this early after the impulsive start, its own pressure; over 100 steps after 50,
    `fishsim validate`: 1.03-1.11 at 0.2-0.3 m/s, 2.0 at 0.1 m/s)."""
    cfg = EvalConfig(speeds=[0.2], frequencies=[], warmup=20, steps=20)
    grid = cfg.tank.grid
    m = evaluate(HydroNetFluid(shipped, grid), NumericalFluid(grid), cfg).metrics["cylinder_0.2"]
    assert m["force_x_ref"] < 0 and m["force_x_net"] < 0
    assert 0.5 < m["drag_ratio"] < 2.0, m


def test_save_load_round_trip_and_deterministic_steps(shipped, tmp_path):
    path = export_model(SHIPPED_HYDRONET, tmp_path / "copy.pt", {"note": "round trip"})
    again = load_hydronet(path)
    grid, state, boundary, params = _scene_after_warmup(batch=2, steps=3)
    with torch.no_grad():
        a = HydroNetFluid(shipped, grid).step(state, boundary, params)
        b = HydroNetFluid(again, grid).step(state, boundary, params)
        c = HydroNetFluid(again, grid).step(state, boundary, params)
    assert torch.equal(a.a, b.a) and torch.equal(a.p, b.p) and torch.equal(b.p, c.p)
    trained = {"rho": [50.0, 50.0], "mu": [1.25e-4, 1.25e-4], "dx": 2.5e-3, "h": 0.01,   # carried over, in both files
               "scene_cells": [64, 128]}                   # the shipped file's from its metadata's pool
    assert json.loads(path.with_suffix(".json").read_text()) == {"note": "round trip", "training_range": trained}
    assert torch.load(path, weights_only=False)["training_range"] == trained == again.training_range
    assert np.isfinite(a.p.numpy()).all() and a.p.abs().max() > 0


def test_a_re_measured_frequency_study_replaces_the_recorded_one_and_keeps_it(tmp_path):
    """``ship --record``: the new study under "swim_studies" with its date and source, the one it
    replaces appended to "swim_studies_earlier", the other entries untouched."""
    from fishsim.learn.ship import record_swim_studies

    meta = tmp_path / "hydronet.json"
    meta.write_text(json.dumps({"net": {}, "swim_studies": {"frames_120": {"old": 1}, "frames_300": {"kept": 1}}}))
    study = tmp_path / "study"
    study.mkdir()
    (study / "metrics.json").write_text(json.dumps({"swim": {"frames": 120}, "fluids": {"hydronet": {}}}))
    out = record_swim_studies((study,), meta)
    assert json.loads(meta.read_text()) == out
    assert out["swim_studies"]["frames_120"]["fluids"] == {"hydronet": {}}
    assert out["swim_studies"]["frames_120"]["from"] == str(study) and "recorded" in out["swim_studies"]["frames_120"]
    assert out["swim_studies_earlier"] == {"frames_120": [{"old": 1}]}
    assert out["swim_studies"]["frames_300"] == {"kept": 1}
