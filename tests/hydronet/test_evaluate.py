"""HydroNet evaluation against the numerical solver (fishsim validate suite=hydronet)."""

import json
import math

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.fluid.hydronet.config import EvalConfig
from fishsim.fluid.numerical import NumericalFluid
from fishsim.fluid.tank import TankConfig
from fishsim.learn.evaluate import Scenes, energy_checks, evaluate, kinetic_energy, summarise

SMALL = EvalConfig(speeds=[0.2], frequencies=[5.0], warmup=3, steps=3,
                   tank=TankConfig(H=40, W=120, dx=5e-3, wall_y=2, wall_x=3), still_steps=3, energy_steps=4)
SMALL_ARGS = ["scenes.speeds=[0.2]", "scenes.frequencies=[5]", "scenes.warmup=3", "scenes.steps=3",
              "scenes.tank.H=40", "scenes.tank.W=120", "scenes.tank.dx=5e-3", "scenes.tank.wall_y=2",
              "scenes.tank.wall_x=3", "scenes.still_steps=3", "scenes.energy_steps=4"]


def test_reference_against_itself_has_zero_error_and_equal_forces():
    """The metrics compare matching states: the numerical solver judged against itself scores 0."""
    grid = SMALL.tank.grid
    out = evaluate(NumericalFluid(grid), NumericalFluid(grid), SMALL)
    for m in out.metrics.values():
        for key, value in m.items():
            if "error" in key:
                assert value == pytest.approx(0.0, abs=1e-6), key
        assert m["force_x_net"] == pytest.approx(m["force_x_ref"])
    cyl = out.metrics["cylinder_0.2"]
    assert cyl["drag_ratio"] == pytest.approx(1.0) and cyl["force_x_ref"] < 0  # drag opposes the tow
    assert summarise(out.metrics)["worst_drag_error"] == pytest.approx(0.0, abs=1e-6)


def test_scenes_move_as_prescribed():
    """The cylinder advances U h per step; the fish stays centred and beats (surface moves)."""
    sc = Scenes(SMALL)
    c0, c1 = sc.surfaces(0)[0].mean(1), sc.surfaces(10)[0].mean(1)
    torch.testing.assert_close(c1 - c0, torch.tensor([[0.2 * 10 * SMALL.h, 0.0]]), atol=1e-6, rtol=0)
    f0, f1 = sc.surfaces(40)[1], sc.surfaces(45)[1]
    assert abs(f0[..., 0].mean().item() - SMALL.tank.size[0] / 2) < 0.01
    assert (f1 - f0).abs().max() > 1e-3
    bd = sc.boundary(10)
    assert bd.mask.shape == (2, 1, SMALL.tank.H, SMALL.tank.W) and math.isclose(bd.mask.max().item(), 1.0, abs_tol=1e-6)


def test_validate_command_writes_metrics_and_picture(tmp_path, monkeypatch):
    """... and judges against `fishsim simulate`'s numerical fluid (the joint stage), the one the
    frequency study's references and train-hydronet's teacher are."""
    import fishsim.learn.evaluate as E
    from fishsim.config import NumericalConfig
    from fishsim.fluid.factory import numerical_stepping
    from tests.test_cli_simulate import _tiny_hydronet

    references = []
    for name in ("evaluate", "energy_checks"):
        real = getattr(E, name)
        monkeypatch.setattr(E, name, lambda net, ref, *a, _f=real, **k: references.append(ref) or _f(net, ref, *a, **k))
    model = _tiny_hydronet(tmp_path / "net.pt")
    result = CliRunner().invoke(app, ["validate", f"hydronet.model_file={model}", *SMALL_ARGS, f"out_dir={tmp_path}"])
    assert result.exit_code == 0, result.output
    stepping = numerical_stepping(NumericalConfig())
    assert len(references) == 2 and all({k: getattr(r, k) for k in stepping} == stepping for r in references)
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert set(data["metrics"]) == {"cylinder_0.2", "fish_5Hz"}
    values = [v for m in data["metrics"].values() for v in m.values()]
    assert np.isfinite(values).all() and data["summary"]["mean_one_step_error_v"] > 0
    assert (tmp_path / "comparison.png").stat().st_size > 10_000


def test_validate_missing_model_exit_code_2(tmp_path):
    result = CliRunner().invoke(app, ["validate", f"hydronet.model_file={tmp_path / 'none.pt'}", f"out_dir={tmp_path}"])
    assert result.exit_code == 2 and "fishsim train-hydronet" in result.output


def test_impossible_scene_grids_are_one_line(tmp_path):
    from typer.testing import CliRunner

    from fishsim.cli import app

    for args, words in ((["scenes.tank.H=20"], "at least 32 x 32"), (["scenes.tank.dx=-1"], "tank.dx must be > 0"),
                        (["scenes.rho=-1"], "rho, mu > 0"),
                        (["scenes.radius=1"], "does not fit")):
        result = CliRunner().invoke(app, ["validate", *args, f"out_dir={tmp_path}"])
        assert result.exit_code == 2 and words in result.output, result.output


def test_energy_checks_are_exact_for_the_reference_itself():
    """The numerical solver judged against itself: a still fish leaves the water at rest (max |v|
    = 0 exactly) and the swimming fish's kinetic energy ratio is 1; E of a uniform stream U over
    a fluid of area A is rho U^2 A / 2."""
    grid = SMALL.tank.grid
    checks = energy_checks(NumericalFluid(grid), NumericalFluid(grid), SMALL)
    assert checks["still_fish_max_speed_3"] == 0.0
    assert checks["kinetic_energy_ref_4"] > 0 and checks["kinetic_energy_ratio"] == pytest.approx(1.0, rel=1e-6)
    from fishsim.fields import FluidState

    U, y = 0.1, torch.arange(grid.H + 1, dtype=torch.float32)[:, None] * grid.dx
    stream = FluidState((U * y).expand(grid.H + 1, grid.W + 1)[None, None], torch.zeros(1, 1, grid.H, grid.W))
    fluid = torch.zeros(1, 1, grid.H, grid.W)
    e = kinetic_energy(stream, fluid, 50.0, grid.dx)            # interior x-faces: H (W - 1) (box walls: 0)
    assert e.item() == pytest.approx(0.5 * 50.0 * U**2 * grid.H * (grid.W - 1) * grid.dx**2, rel=1e-5)
