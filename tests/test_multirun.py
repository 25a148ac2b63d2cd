"""Sweeps (fishsim/multirun.py): `-m` runs one job per combination through Hydra's launchers,
one folder per job, and collects every job's summary in summary.csv."""

import csv

import pytest
from typer.testing import CliRunner

from fishsim.cli import app

runner = CliRunner()
TINY = ["fish.edge_length=5e-3", "preview=false"]


def _rows(folder):
    with open(folder / "summary.csv") as fh:
        return list(csv.DictReader(fh))


def test_a_two_job_joblib_sweep_writes_a_folder_per_job_and_one_table(tmp_path, monkeypatch):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["mesh", "-m", "fish.min_angle=25,30", *TINY, "hydra/launcher=joblib",
                                 "hydra.launcher.n_jobs=2", "hydra.sweep.dir=sweep"])
    assert result.exit_code == 0, result.output
    rows = _rows(tmp_path / "sweep")
    assert [r["job"] for r in rows] == ["0", "1"] and all(r["status"] == "complete" for r in rows)
    assert "fish.min_angle=25" in rows[0]["overrides"] and "fish.min_angle=30" in rows[1]["overrides"]
    for job in ("0", "1"):
        assert (tmp_path / "sweep" / job / "fish.vtu").exists()
        assert (tmp_path / "sweep" / job / ".hydra" / "overrides.yaml").exists()
    assert float(rows[0]["min angle [deg]"]) >= 25 and float(rows[1]["min angle [deg]"]) >= 30


def test_a_failing_job_is_recorded_and_the_others_complete(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["mesh", "-m", "fish.edge_length=5e-3,0.05", "preview=false", "hydra.sweep.dir=s"])
    assert result.exit_code == 2 and "1 of 2 jobs failed (jobs 1)" in result.output
    rows = _rows(tmp_path / "s")
    assert rows[0]["status"] == "complete" and rows[1]["status"].startswith("failed: fish.edge_length=0.05")


def test_a_config_wrong_for_every_job_fails_before_launching(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["mesh", "-m", "fish.edge_length=4e-3,5e-3", "fish.bogus=1"])
    assert result.exit_code == 2 and "unknown config key 'fish.bogus'" in result.output
    assert not (tmp_path / "multirun").exists()


def test_the_shipped_slurm_launcher_config_composes():
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    from hydra import compose, initialize_config_dir

    from fishsim.config import config_dir

    with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
        cfg = compose(config_name="simulate", overrides=["hydra/launcher=slurm", "hydra.launcher.partition=gpu"],
                      return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher")
    assert cfg.hydra.launcher.cpus_per_task == 2 and cfg.hydra.launcher.partition == "gpu"


def test_a_sweep_through_submitit_runs_each_job_as_a_submitit_job(tmp_path, monkeypatch):
    """Hydra's submitit launcher, the one behind hydra/launcher=slurm, with its local executor:
    each job runs in its own submitit-managed process and lands in the sweep's table (a SLURM
    cluster swaps only the executor)."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["mesh", "-m", "fish.min_angle=25,30", *TINY, "hydra/launcher=submitit_local",
                                 "hydra.sweep.dir=sweep"])
    assert result.exit_code == 0, result.output
    rows = _rows(tmp_path / "sweep")
    assert [r["status"] for r in rows] == ["complete", "complete"]
    assert any((tmp_path / "sweep" / ".submitit").rglob("*_result.pkl"))      # submitit ran them
