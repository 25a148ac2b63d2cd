"""The CLI shell and the structured configs: bad input gives one line and exit code 2."""

import pytest
from typer.testing import CliRunner

from fishsim.cli import app
from fishsim.config import load_config, to_yaml
from fishsim.errors import ConfigError

runner = CliRunner()


def test_defaults_compose_and_validate():
    cfg = load_config("mesh")
    assert cfg.fish.length == pytest.approx(0.2)
    assert cfg.fish.edge_length == pytest.approx(2e-3)
    assert "edge_length" in to_yaml(cfg)


def test_override_applies():
    cfg = load_config("mesh", ["fish.edge_length=3e-3", "output=x.msh"])
    assert cfg.fish.edge_length == pytest.approx(3e-3)
    assert cfg.output == "x.msh"


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("fish.foo=1", "unknown config key 'fish.foo'"),
        ("bogus=3", "unknown config key 'bogus'"),
        ("fish.length=-1", "fish.length must be > 0"),
        ("fish.length=abc", "could not be converted"),
        ("fish.profile=zigzag", "fish.profile must be"),
        ("fish=nope", "Could not find 'fish/nope'"),
        ("~fish.length", "'~fish.length' deletes a setting, which keeps its default"),
    ],
)
def test_bad_config_is_one_clear_line(override, fragment):
    with pytest.raises(ConfigError, match=None) as err:
        load_config("mesh", [override])
    assert fragment in str(err.value)
    assert "\n" not in str(err.value)


def test_free_form_dicts_take_new_keys_without_a_plus():
    """Keys inside a dict-valued option (optimizer.options, optimizer.submitit) are new to the
    composed config; they are accepted as plain overrides, while a misspelt option stays unknown."""
    o = load_config("optimize", ["optimizer.options={betas:[0.9,0.99]}", "optimizer.submitit.cluster=local"]).optimizer
    assert o.options == {"betas": [0.9, 0.99]} and o.submitit == {"cluster": "local"}
    with pytest.raises(ConfigError, match="unknown config key 'optimizer.submitt.cluster'"):
        load_config("optimize", ["optimizer.submitt.cluster=local"])


def test_fluid_precision_is_float32_or_float64():
    assert load_config("simulate", ["fluid.dtype=float64"]).fluid.dtype == "float64"
    with pytest.raises(ConfigError, match="fluid.dtype must be float32 or float64"):
        load_config("simulate", ["fluid.dtype=float16"])


def test_each_fluid_model_has_its_own_keys_and_the_tank_its_group():
    """fluid=<model> picks that model's config class; another model's key, or a tank key under
    fluid, is refused in one line that says where it belongs."""
    from fishsim.config import HydroNetConfig, NumericalConfig, VacuumConfig

    kinds = {m: type(load_config("simulate", [f"fluid={m}"]).fluid) for m in ("numerical", "hydronet", "none")}
    assert kinds == {"numerical": NumericalConfig, "hydronet": HydroNetConfig, "none": VacuumConfig}
    cfg = load_config("simulate", ["tank=long", "tank.wall_x=4", "origin=[0.06,0.25]"])
    assert (cfg.tank.H, cfg.tank.W, cfg.tank.wall_x, cfg.tank.dx) == (200, 800, 4, 2.5e-3)
    for overrides, fragment in ((["fluid.H=40"], "is a setting of the tank: use tank.H"),
                                (["fluid=hydronet", "fluid.substeps=4"], "unknown config key 'fluid.substeps'"),
                                (["fluid.model=hydronet"], "fluid.refinement is not a setting of fluid=hydronet"),
                                (["tank.H=8"], "at least 16 x 16 cells"),
                                (["tank.inflow=0.1", "tunnel=true"], "drop tank.inflow=0.1")):
        with pytest.raises(ConfigError) as err:
            load_config("simulate", overrides)
        assert fragment in str(err.value) and "\n" not in str(err.value), (overrides, str(err.value))


def test_config_files_of_either_layout_and_any_fluid_load(tmp_path):
    """A stored config names its fluid model (a HydroNet run's replaces the default numerical
    fluid), and one written before the tank group (the grid, walls and inflow inside one flat
    fluid node with every model's keys) loads into today's layout."""
    hydronet = tmp_path / "hydronet.yaml"
    hydronet.write_text(to_yaml(load_config("simulate", ["fluid=hydronet", "fluid.bf16=true", "tank.W=200"])))
    cfg = load_config("simulate", ["frames=3"], str(hydronet))
    assert (cfg.fluid.model, cfg.fluid.bf16, cfg.tank.W, cfg.frames) == ("hydronet", True, 200, 3)
    legacy = tmp_path / "legacy.yaml"
    legacy.write_text("fluid:\n  model: hydronet\n  H: 64\n  W: 128\n  dx: 0.003\n  wall_y: 2\n  wall_x: 4\n"
                      "  inflow: 0.0\n  substeps: 8\n  pressure: recovered\n  rho: 40.0\norigin: [0.05, 0.08]\n")
    cfg = load_config("simulate", [], str(legacy))
    assert (cfg.tank.H, cfg.tank.W, cfg.tank.dx, cfg.tank.wall_y, cfg.tank.wall_x) == (64, 128, 0.003, 2, 4)
    assert (cfg.fluid.model, cfg.fluid.pressure, cfg.fluid.rho) == ("hydronet", "recovered", 40.0)


def test_penalization_rate_is_positive_or_null():
    assert load_config("simulate", []).fluid.penalization_rate == 2400
    split = ["fluid.implicit=false"]
    assert load_config("simulate", [*split, "fluid.penalization_rate=null"]).fluid.penalization_rate is None
    with pytest.raises(ConfigError, match=r"fluid.penalization_rate must be > 0 \(1/s\) or null"):
        load_config("simulate", ["fluid.penalization_rate=0"])


def test_implicit_needs_the_rate_and_no_brinkman():
    assert load_config("simulate", []).fluid.implicit is True
    for bad in ("fluid.penalization_rate=null", "fluid.brinkman=1e4"):
        with pytest.raises(ConfigError, match=r"fluid.implicit=true \(the default\) solves for "
                                              r"fluid.penalization_rate.*add fluid.implicit=false"):
            load_config("simulate", [bad])


def test_brinkman_is_positive_or_null():
    assert load_config("simulate", ["fluid.implicit=false", "fluid.brinkman=1e4"]).fluid.brinkman == 1e4
    with pytest.raises(ConfigError, match=r"fluid.brinkman must be > 0 \(1/s\) or null"):
        load_config("simulate", ["fluid.brinkman=-5"])


def test_cli_bad_key_exit_code_2_no_traceback():
    result = runner.invoke(app, ["mesh", "fish.nonsense=1"])
    assert result.exit_code == 2
    out = result.output
    assert "unknown config key 'fish.nonsense'" in out
    assert "Traceback" not in out
    assert len([line for line in out.splitlines() if line.strip()]) == 1


def test_help_lists_config_groups():
    result = runner.invoke(app, ["mesh", "--help"])
    assert result.exit_code == 0
    assert "fish.edge_length" in result.output
    nested = runner.invoke(app, ["simulate", "--help"], terminal_width=200)      # groups inside groups
    assert "solid.material.youngs_modulus" in nested.output and "solid.pd.atol" in nested.output
    optimize = runner.invoke(app, ["optimize", "--help"], terminal_width=200)
    assert "optimizer.methods" in optimize.output and "objective.name" in optimize.output


def test_show_config_prints_yaml():
    result = runner.invoke(app, ["mesh", "--show-config", "fish.length=0.3"])
    assert result.exit_code == 0
    assert "length: 0.3" in result.output


def test_only_built_commands_are_listed():
    result = runner.invoke(app, ["--help"])
    assert "mesh" in result.output
    for built in ("mesh", "simulate", "render", "train-hydronet", "validate", "optimize"):
        assert built in result.output


def test_shipped_yaml_defaults_equal_the_code_defaults():
    """conf/*.yaml and the dataclass defaults say the same thing (a recalibrated constant cannot
    be left behind in one of them)."""
    from fishsim.config import MeshCommandConfig, SimulateConfig, load_config
    from fishsim.fluid.hydronet.config import TrainConfig
    from fishsim.learn.train import train_config

    assert load_config("simulate") == SimulateConfig()
    from fishsim.config import FLUID_MODELS

    for model, kind in FLUID_MODELS.items():
        assert load_config("simulate", [f"fluid={model}"]).fluid == kind()
    assert load_config("mesh") == MeshCommandConfig()
    assert train_config(load_config("train-hydronet")) == TrainConfig()
    from fishsim.config import ValidateConfig

    assert load_config("validate") == ValidateConfig()


def test_config_file_missing_or_unreadable_is_exit_2(tmp_path):
    missing = runner.invoke(app, ["simulate", "--config", str(tmp_path / "nope.yaml"), "frames=1"])
    assert missing.exit_code == 2 and "does not exist" in missing.output
    bad = tmp_path / "bad.yaml"
    bad.write_text("frames: [unclosed\n")
    broken = runner.invoke(app, ["simulate", "--config", str(bad)])
    assert broken.exit_code == 2 and "not a readable YAML config" in broken.output
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("framez: 3\n")
    typo = runner.invoke(app, ["simulate", "--config", str(unknown)])
    assert typo.exit_code == 2 and "framez" in typo.output


def test_version():
    from fishsim import __version__

    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"fishsim {__version__}"


def test_top_level_help_and_version_do_not_import_torch():
    """`fishsim --help` / `--version` stay fast (0.13 s here, was 2.2 s): the config dataclasses
    are imported only for a command's own help or run."""
    import subprocess
    import sys

    code = ("import sys\nfrom typer.testing import CliRunner\nfrom fishsim.cli import app\n"
            "r = CliRunner()\nassert r.invoke(app, ['--help']).exit_code == 0\n"
            "assert r.invoke(app, ['--version']).exit_code == 0\nprint('torch' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_config_and_command_help_do_not_import_torch():
    """Every command's help stays fast (`fishsim simulate --help` 0.25 s here, was 1.85 s;
    `fishsim train-hydronet --help` 0.25 s, was 1.7 s): fishsim.config takes its dataclasses from
    the parts' light config modules, which import neither torch nor numpy nor numba."""
    import subprocess
    import sys

    code = ("import sys\nimport fishsim.config\nfrom typer.testing import CliRunner\nfrom fishsim.cli import app\n"
            "for name in ('mesh', 'simulate', 'train-hydronet', 'validate', 'optimize', 'render'):\n"
            "    assert CliRunner().invoke(app, [name, '--help']).exit_code == 0, name\n"
            "print(sorted({'torch', 'numpy', 'numba'} & set(sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_simulate_help_lists_every_config_group():
    """The help's config list, built from the parts' config modules: every group, nested groups
    included, with its keys and defaults."""
    out = runner.invoke(app, ["simulate", "--help"], terminal_width=400).output
    assert "top level: frames=200" in out
    for group in ("fish", "solid", "controller", "batch", "fluid", "coupling"):
        assert f"{group}: {group}." in out, group
    for key in ("solid.material.youngs_modulus=600000.0", "solid.pd.preconditioner=lagged_newton",
                "fluid.pressure=network", "coupling.distance=segment", "coupling.force_mode=per_node"):
        assert key in out, key


def test_validate_judges_the_hydronet_node_a_hydronet_config():
    """validate's HydroNet is a ``hydronet`` node composed from the shipped conf/fluid/hydronet.yaml
    (``fluid@hydronet``): the same HydroNetConfig as simulate's fluid=hydronet, set as hydronet.*,
    its messages naming hydronet.*; its help lists that model's keys only."""
    from fishsim.config import HydroNetConfig

    node = load_config("validate").hydronet
    assert type(node) is HydroNetConfig and node == HydroNetConfig() == load_config("simulate", ["fluid=hydronet"]).fluid
    cfg = load_config("validate", ["hydronet.model_file=net.pt", "hydronet.bf16=true", "hydronet.pressure=recovered",
                                   "hydronet.strict_range=true"])
    assert (cfg.hydronet.model_file, cfg.hydronet.bf16, cfg.hydronet.pressure, cfg.hydronet.strict_range) == (
        "net.pt", True, "recovered", True)
    for override, fragment in (("hydronet.pressure=own", "hydronet.pressure must be recovered or network"),
                               ("hydronet.model=numerical", "hydronet.model must be hydronet"),
                               ("hydronet.substeps=4", "unknown config key 'hydronet.substeps'"),
                               ("hydronet.rho=40", "hydronet.rho stays at its default"),
                               ("hydronet.dtype=float64", "hydronet.dtype stays at its default")):
        with pytest.raises(ConfigError) as err:
            load_config("validate", [override])
        assert fragment in str(err.value) and "\n" not in str(err.value), (override, str(err.value))
    out = runner.invoke(app, ["validate", "--help"], terminal_width=400).output
    assert "hydronet.model_file=None" in out and "hydronet=numerical" not in out


def test_validate_hydronet_settings_reach_the_evaluation_and_the_studies(tmp_path, monkeypatch):
    """suite=hydronet evaluates the network that hydronet.* describes (the file, its precision and
    pressure); the studies' HydroNet runs get the node's model and precision, suite=solid its
    pressure too, while suite=swim's fluids keep choosing theirs and its own hydronet_overrides
    come last."""
    import fishsim.learn.evaluate
    from fishsim.commands.validate import hydronet_overrides, run
    from tests.test_cli_simulate import _tiny_hydronet

    class Judged(Exception):
        pass

    def evaluate(net, reference, scenes, device, progress=None):
        raise Judged(net)

    monkeypatch.setattr(fishsim.learn.evaluate, "evaluate", evaluate)
    model = _tiny_hydronet(tmp_path / "net.pt")
    cfg = load_config("validate", [f"hydronet.model_file={model}", "hydronet.bf16=true", "hydronet.pressure=recovered",
                                   f"out_dir={tmp_path / 'o'}"])
    with pytest.raises(Judged) as judged:
        run(cfg)
    net = judged.value.args[0]
    assert (net.model.cfg.hidden, net.bf16, net.pressure) == (4, True, "recovered")      # the file's net, not the shipped one
    studies = hydronet_overrides(cfg)
    assert f"fluid.model_file={model}" in studies and "fluid.bf16=true" in studies
    assert not any(o.startswith("fluid.pressure=") for o in studies)
    assert "fluid.pressure=recovered" in hydronet_overrides(cfg, pressure=True)
    assert load_config("simulate", ["fluid=hydronet", *hydronet_overrides(cfg, pressure=True)]).fluid == cfg.hydronet


@pytest.mark.parametrize("old, new", [("model_file=net.pt", "hydronet.model_file"), ("bf16=true", "hydronet.bf16"),
                                      ("pressure=recovered", "hydronet.pressure"), ("+model_file=net.pt",
                                                                                   "hydronet.model_file")])
def test_validate_old_top_level_hydronet_keys_are_one_line(old, new):
    """The keys validate had before its hydronet node are refused in one line that names the new
    key (as fluid.H names tank.H), exit code 2; other commands do not suggest it."""
    result = runner.invoke(app, ["validate", old])
    key = old.lstrip("+").split("=")[0]
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert result.output.strip() == f"error: config error: '{key}' is a setting of the HydroNet validate judges: use {new}"
    with pytest.raises(ConfigError, match="unknown config key 'model_file'"):
        load_config("simulate", ["model_file=net.pt"])


def test_validate_config_stored_before_the_hydronet_node_loads(tmp_path):
    """A validate config stored before 2026-11-27 (a run's .hydra/config.yaml, as in results/):
    the top-level model_file, bf16 and pressure load with --config into the hydronet node, the
    scenes' grid and walls into scenes.tank."""
    old = tmp_path / "config.yaml"
    old.write_text("suite: hydronet\nmodel_file: net.pt\nbf16: true\npressure: recovered\ndevice: cpu\n"
                   "scenes:\n  steps: 5\n  H: 64\n  W: 128\n  dx: 0.003\n  wall_x: 4\n")
    cfg = load_config("validate", ["scenes.steps=3"], str(old))
    assert (cfg.hydronet.model_file, cfg.hydronet.bf16, cfg.hydronet.pressure, cfg.scenes.steps) == (
        "net.pt", True, "recovered", 3)
    assert load_config("validate", [], str(old)) == load_config(
        "validate", ["hydronet.model_file=net.pt", "hydronet.bf16=true", "hydronet.pressure=recovered",
                     "scenes.steps=5", "scenes.tank.H=64", "scenes.tank.W=128", "scenes.tank.dx=0.003",
                     "scenes.tank.wall_x=4"])
