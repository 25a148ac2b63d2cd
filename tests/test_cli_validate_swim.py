"""fishsim validate suite=swim on a small tank: the study's table, metrics and plot, and its
statistics against hand-made values."""

import json

import numpy as np
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.swim_study import compare, spearman

runner = CliRunner()


def test_spearman_against_hand_values():
    assert spearman([1, 2, 3, 4], [10, 20, 30, 40]) == 1.0
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1]) == -1.0
    assert abs(spearman([1, 2, 3, 4, 5], [2, 1, 4, 3, 5]) - 0.8) < 1e-12      # 1 - 6 * 4 / (5 * 24)
    assert np.isnan(spearman([1, 2], [1, np.nan]))                                # one entry left
    # a fish that blew up (NaN) is left out: ranks [1, 2, 3, 4] against [1, 2, 4, 3]
    assert abs(spearman([1, 2, 3, 4, 5], [1, 2, 4, 3, np.nan]) - 0.8) < 1e-12    # 1 - 6 * 2 / (4 * 15)


def test_compare_mismatch_and_argmax():
    ref = {"displacement_mm": [10.0, 30.0, 20.0], "dx_mm": 2.5}
    other = {"displacement_mm": [5.0, 25.0, 35.0], "dx_mm": 2.5}
    c = compare(other, ref, [3.0, 5.0, 7.0])
    assert c["argmax_hz"] == 7.0 and c["mean_mismatch_mm"] == 25.0 / 3 and c["mean_mismatch_cells"] == 25.0 / 7.5
    assert c["spearman"] == 0.5


def test_validate_swim_small(tmp_path):
    small = "['tank.H=32','tank.W=96','fish.length=0.06','fish.edge_length=4e-3','origin=[0.05,0.04]']"
    result = runner.invoke(app, ["validate", "suite=swim", "swim.frequencies=[4,8]", "swim.frames=6",
                                 "swim.fluids=[numerical_r2,numerical]", f"swim.overrides={small}",
                                 f"out_dir={tmp_path}"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    ref, r1 = metrics["fluids"]["numerical_r2"], metrics["fluids"]["numerical"]
    assert abs(ref["spearman"] - 1.0) < 1e-12 and ref["mean_mismatch_mm"] == 0.0
    assert len(r1["displacement_mm"]) == 2 and np.isfinite(r1["displacement_mm"]).all()
    assert r1["displacement_mm"] != ref["displacement_mm"]
    drift = np.asarray(r1["lateral_drift_mm"])              # the centroid's y displacement: small in 6 frames
    assert drift.shape == (2,) and np.isfinite(drift).all() and (np.abs(drift) < 2.5).all(), drift   # < 1 cell
    assert (tmp_path / "swim.png").exists() and "Spearman" in result.output


def test_validate_swim_bad_fluid_is_exit_2(tmp_path):
    result = runner.invoke(app, ["validate", "suite=swim", "swim.fluids=[comsol]", f"out_dir={tmp_path}"])
    assert result.exit_code == 2 and "unknown ['comsol']" in result.output


def test_validate_swim_judges_the_given_model_file(tmp_path):
    """hydronet.model_file= reaches the study's HydroNet runs: a missing file is refused (it used to be
    ignored, and the shipped model judged instead)."""
    result = runner.invoke(app, ["validate", "suite=swim", "swim.fluids=[hydronet]", "swim.reference=hydronet",
                                 "swim.frames=2", f"hydronet.model_file={tmp_path / 'missing.pt'}", f"out_dir={tmp_path / 'o'}"])
    assert result.exit_code == 2 and "missing.pt" in result.output, result.output
    small = "['tank.H=32','tank.W=96','fish.length=0.06','fish.edge_length=4e-3','origin=[0.05,0.04]']"
    numerical = runner.invoke(app, ["validate", "suite=swim", "swim.frequencies=[4,8]", "swim.frames=2",
                                    "swim.fluids=[numerical]", "swim.reference=numerical", f"swim.overrides={small}",
                                    f"hydronet.model_file={tmp_path / 'missing.pt'}", f"out_dir={tmp_path / 'n'}"])
    assert numerical.exit_code == 0, numerical.output                 # the numerical runs do not take it


def test_validate_swim_reuses_a_stored_reference(tmp_path):
    """swim.reuse= reads the fluids of an earlier study with the same frequencies, frames and
    overrides (the stored numbers, here altered by hand, are what the new study compares with),
    re-runs a HydroNet fluid whose model differs, and refuses a study that asked another question."""
    small = "['tank.H=32','tank.W=96','fish.length=0.06','fish.edge_length=4e-3','origin=[0.05,0.04]']"
    study = ["validate", "suite=swim", "swim.frequencies=[4,8]", "swim.frames=2", "swim.reference=numerical",
             f"swim.overrides={small}"]
    first = runner.invoke(app, [*study, "swim.fluids=[numerical]", f"out_dir={tmp_path / 'a'}"])
    assert first.exit_code == 0, first.output
    stored = json.loads((tmp_path / "a" / "metrics.json").read_text())
    stored["fluids"]["numerical"]["displacement_mm"] = [1.0, 3.0]
    (tmp_path / "a" / "metrics.json").write_text(json.dumps(stored))
    both = [*study, "swim.fluids=[numerical,hydronet]", f"swim.reuse={tmp_path / 'a' / 'metrics.json'}"]
    second = runner.invoke(app, [*both, f"out_dir={tmp_path / 'b'}"])
    assert second.exit_code == 0, second.output
    fluids = json.loads((tmp_path / "b" / "metrics.json").read_text())["fluids"]
    assert fluids["numerical"]["displacement_mm"] == [1.0, 3.0] and "reused_from" in fluids["numerical"]
    net = fluids["hydronet"]
    assert "reused_from" not in net and np.isfinite(net["displacement_mm"]).all()
    assert net["mean_mismatch_mm"] == np.mean(np.abs(np.asarray(net["displacement_mm"]) - [1.0, 3.0]))
    third = runner.invoke(app, [*study, "swim.fluids=[numerical,hydronet]", f"out_dir={tmp_path / 'c'}",
                                f"swim.reuse={tmp_path / 'b' / 'metrics.json'}"])          # the same model: both read
    assert third.exit_code == 0, third.output
    again = json.loads((tmp_path / "c" / "metrics.json").read_text())["fluids"]
    assert again["hydronet"]["displacement_mm"] == net["displacement_mm"] and "reused_from" in again["hydronet"]
    longer = runner.invoke(app, [*both, "swim.frames=3", f"out_dir={tmp_path / 'd'}"])
    assert longer.exit_code == 2 and "frames" in longer.output, longer.output
    missing = runner.invoke(app, [*study, "swim.fluids=[numerical]", f"swim.reuse={tmp_path / 'none.json'}",
                                  f"out_dir={tmp_path / 'e'}"])
    assert missing.exit_code == 2 and "none.json" in missing.output, missing.output
