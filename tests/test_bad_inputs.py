"""Bad inputs to every command: one line on stderr, exit code 2, no traceback, and nothing left
behind (no empty run folder, no stray lock file) -- for unusable out_dirs, outputs that name a
folder, input errors found after the run folder was made, train-hydronet's folder and resume
rules, Hydra runner settings, and a HydroNet run outside the fluid its model was trained for."""

from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.fluid.factory import SHIPPED_HYDRONET
from fishsim.fluid.hydronet import load_hydronet
from fishsim.fluid.hydronet.trained_range import check_channel, check_fluid, outside

runner = CliRunner()
TINY_SIM = ["fluid=none", "fish.edge_length=5e-3", "frames=2"]
TINY_TRAIN = ["iterations=2", "batch_size=2", "net.hidden=4", "net.depth=2", "pool.size=4", "pool.H=16", "pool.W=32",
              "pool.fish_length=[0.04,0.05]", "pool.obstacle_cells=[2,3]", "val_every=1000000", "threads=1",
              "compile_loss=false", "progress=false"]
COMMANDS = {"mesh": ["fish.edge_length=5e-3"], "simulate": TINY_SIM, "render": ["path=x.h5"], "validate": [],
            "optimize": TINY_SIM, "train-hydronet": TINY_TRAIN}


def _one_line_error(result, *words: str) -> None:
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2 and len(lines) == 1 and lines[0].startswith("error:"), result.output
    for w in words:
        assert w in lines[0], lines[0]


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@pytest.fixture
def here(tmp_path, monkeypatch) -> Path:
    """A fresh working folder holding a file, a folder and a junk trajectory x.h5."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir").mkdir()
    (tmp_path / "x.h5").write_text("not an HDF5 file")
    return tmp_path


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize("out_dir, words", [("afile", "is a file, not a folder"), ("afile/sub", "cannot create out_dir"),
                                            ("/proc", "cannot write in out_dir")])
def test_an_unusable_out_dir_is_one_line(here, command, out_dir, words):
    before = _files(here)
    _one_line_error(runner.invoke(app, [command, *COMMANDS[command], f"out_dir={out_dir}"]), words)
    assert _files(here) == before


@pytest.mark.parametrize("command, example", [("simulate", "trajectory.h5"), ("mesh", "fish.vtu")])
def test_an_output_naming_a_folder_is_one_line(here, command, example):
    result = runner.invoke(app, [command, *COMMANDS[command], "out_dir=new", f"output={here / 'adir'}"])
    _one_line_error(result, "is a folder", f"output={example}")
    assert not (here / "new").exists() and not any((here / "adir").iterdir())


@pytest.mark.parametrize("command, bad", [
    ("mesh", "fish.mesh_file=missing.vtu"), ("mesh", "output=fish.stl"), ("simulate", "fish.mesh_file=missing.vtu"),
    ("render", "path=x.h5"), ("validate", "hydronet.model_file=missing.pt"), ("optimize", "fish.mesh_file=missing.vtu"),
    ("train-hydronet", "init_from=missing.pt")])
@pytest.mark.parametrize("out_dir", [None, "new/run", "adir"])
def test_an_input_error_leaves_no_folder_behind(here, command, bad, out_dir):
    """Default folders (outputs/<command>/<time>), a new out_dir and an existing empty one: after
    the error the working folder is as it was."""
    before = _files(here)
    args = [command, *COMMANDS[command], bad] + ([f"out_dir={out_dir}"] if out_dir else [])
    result = runner.invoke(app, args)
    assert result.exit_code == 2 and result.output.startswith("error:"), result.output
    assert _files(here) == before


def test_train_hydronet_writes_to_a_new_run_folder_by_default(here):
    first, second = (runner.invoke(app, ["train-hydronet", *TINY_TRAIN]) for _ in range(2))
    assert first.exit_code == second.exit_code == 0, first.output + second.output
    runs = sorted((here / "outputs" / "train-hydronet").iterdir())
    assert len(runs) == 2 and all((r / "ckpt.pt").exists() and (r / "log.csv").exists() for r in runs)
    assert not (here / "runs").exists()


def test_train_hydronet_resume_needs_the_run_folder(here):
    _one_line_error(runner.invoke(app, ["train-hydronet", *TINY_TRAIN, "resume=true"]), "resume=true needs out_dir=")
    assert _files(here) == {"afile", "adir", "x.h5"}


def test_train_hydronet_never_restarts_over_a_run_unasked(here):
    """A second run into a run's folder is refused (ckpt.pt unchanged) unless it resumes, or
    overwrites (then log.csv starts again: 2 rows, not the old run's 3 plus 2)."""
    assert runner.invoke(app, ["train-hydronet", *TINY_TRAIN, "log_every=1", "out_dir=run"]).exit_code == 0
    saved = (here / "run" / "ckpt.pt").read_bytes()
    _one_line_error(runner.invoke(app, ["train-hydronet", *TINY_TRAIN, "out_dir=run"]), "resume=true", "overwrite=true")
    assert (here / "run" / "ckpt.pt").read_bytes() == saved
    more = runner.invoke(app, ["train-hydronet", *TINY_TRAIN, "log_every=1", "out_dir=run", "resume=true", "iterations=3"])
    assert more.exit_code == 0 and torch.load(here / "run" / "ckpt.pt", weights_only=False)["iteration"] == 3
    again = runner.invoke(app, ["train-hydronet", *TINY_TRAIN, "log_every=1", "out_dir=run", "overwrite=true"])
    assert again.exit_code == 0 and len((here / "run" / "log.csv").read_text().splitlines()) == 1 + 2


@pytest.mark.parametrize("args", [["hydra.sweeper.foo=1"], ["hydra/launcher=joblib"], ["hydra/sweeper=optuna"],
                                  ["hydra.launcher.n_jobs=2"], ["hydra.mode=MULTIRUN"], ["+hydra.foo=1"],
                                  ["controller.frequency=1,2"]])
def test_hydra_runner_settings_are_one_line(here, args):
    """Without -m Hydra's sweeper and launcher settings would silently do nothing: refused."""
    _one_line_error(runner.invoke(app, ["simulate", *TINY_SIM, *args]), "batch.frequency=[3,4,5]")
    assert _files(here) == {"afile", "adir", "x.h5"}


PAPER_FLUID = {"rho": [50.0, 50.0], "mu": [1.25e-4, 1.25e-4], "dx": 2.5e-3, "h": 0.01}


def test_the_shipped_model_knows_its_training_fluid():
    assert load_hydronet(SHIPPED_HYDRONET).training_range == {**PAPER_FLUID, "scene_cells": [64, 128]}
    assert outside(PAPER_FLUID, 50.0, 1.25e-4, 2.5e-3, 0.01) == []
    assert outside(PAPER_FLUID, 1000.0, 1e-3, 2.5e-3, 0.02) == ["rho = 1000", "mu = 0.001", "h = 0.02"]


def test_a_fluid_outside_the_training_range_warns_or_is_refused(here, capsys):
    model = load_hydronet(SHIPPED_HYDRONET)
    assert check_fluid(model, "m.pt", 50.0, 1.25e-4, 2.5e-3, 0.01, strict=True) is None
    message = check_fluid(model, "m.pt", 1000.0, 1e-3, 2.5e-3, 0.01, strict=False)
    assert "rho in [50, 50]" in message and "rho = 1000, mu = 0.001" in message
    assert capsys.readouterr().err.startswith("warning: HydroNet m.pt was trained for")
    strict = runner.invoke(app, ["simulate", "fluid=hydronet", "fluid.rho=1000", "fluid.mu=1e-3", "fluid.strict_range=true",
                                 "fish.edge_length=5e-3", "frames=1"])
    _one_line_error(strict, "was trained for rho in [50, 50] kg/m^3, mu in [0.000125, 0.000125] Pa s", "rho = 1000",
                    "fluid=numerical", "strict_range=true refuses it")
    assert _files(here) == {"afile", "adir", "x.h5"}


def test_a_channel_flow_longer_than_hydronet_s_scenes_warns_or_is_refused(here, capsys):
    """The shipped HydroNet learned channel flows on 64 x 128-cell scenes (its metadata's pool):
    a swim tunnel or inflow through a longer tank warns, or is refused with strict_range."""
    model = load_hydronet(SHIPPED_HYDRONET)
    assert model.training_range["scene_cells"] == [64, 128]
    assert check_channel(model, "m.pt", 128, strict=True) is None
    assert "300-cell tank" in check_channel(model, "m.pt", 300, strict=False)
    assert capsys.readouterr().err.startswith("warning: HydroNet m.pt learned channel flows on scenes of 64 x 128")
    strict = runner.invoke(app, ["simulate", "fluid=hydronet", "tunnel=true", "fluid.strict_range=true",
                                 "fish.edge_length=5e-3", "frames=1"])
    _one_line_error(strict, "its flow does not cross", "fluid=numerical", "strict_range=true refuses it")
    assert _files(here) == {"afile", "adir", "x.h5"}
