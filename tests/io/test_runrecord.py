"""The run record (Hydra's run-folder convention): a run leaves its resolved config, overrides,
version, git commit and console log beside its outputs; the recorded config runs again."""

from omegaconf import OmegaConf
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.io.runrecord import MAX_LOG_LINES, log_text

runner = CliRunner()


def test_a_run_leaves_its_config_overrides_version_and_log(tmp_path):
    out = tmp_path / "run"
    result = runner.invoke(app, ["mesh", f"out_dir={out}", "fish.edge_length=5e-3", "preview=false"])
    assert result.exit_code == 0, result.output
    about = OmegaConf.load(out / ".hydra" / "fishsim.yaml")
    assert about.command == "mesh" and about.status == "complete" and about.fishsim_version
    assert len(about.git_commit) in (40, len("unknown"))
    assert list(OmegaConf.load(out / ".hydra" / "overrides.yaml")) == [f"out_dir={out}", "fish.edge_length=5e-3",
                                                                      "preview=false"]
    assert OmegaConf.load(out / ".hydra" / "config.yaml").fish.edge_length == 5e-3
    assert "nodes" in (out / "mesh.log").read_text()
    again = tmp_path / "again"
    result = runner.invoke(app, ["mesh", "--config", str(out / ".hydra" / "config.yaml"), f"out_dir={again}"])
    assert result.exit_code == 0, result.output
    assert (again / "fish.vtu").read_bytes() == (out / "fish.vtu").read_bytes()


def test_log_text_drops_control_codes_overwritten_text_and_keeps_its_ends():
    assert log_text("\x1b[1mbold\x1b[0m\nloading 10%\rloading 100%\n") == "bold\nloading 100%\n"
    long = "\n".join(str(k) for k in range(3 * MAX_LOG_LINES))
    lines = log_text(long).split("\n")
    assert len(lines) == MAX_LOG_LINES + 1 and lines[0] == "0" and lines[-1] == str(3 * MAX_LOG_LINES - 1)
    assert "lines left out" in lines[MAX_LOG_LINES // 2]


def test_hydra_run_dir_is_the_output_folder(tmp_path):
    out = tmp_path / "hydra_dir"
    result = runner.invoke(app, ["mesh", f"hydra.run.dir={out}", "fish.edge_length=5e-3", "preview=false"])
    assert result.exit_code == 0, result.output
    assert (out / "fish.vtu").exists() and (out / ".hydra" / "config.yaml").exists()
