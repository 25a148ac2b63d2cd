"""The ``fishsim`` command line: each command composes its Hydra config from ``fishsim/conf``,
applies ``key=value`` overrides, validates it, and calls a plain ``run(cfg)``. Nothing else."""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable

import typer
from typer.core import TyperCommand

from fishsim.errors import ConfigError, FishsimError, Terminated, stops_surface

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="fishsim: a fast, differentiable simulator of soft swimming robots.  "
    "Every command takes Hydra-style overrides: `fishsim simulate controller.frequency=6`.",
)

OVERRIDES = typer.Argument(None, help="Config overrides, key=value (e.g. fish.edge_length=3e-3).",
                           show_default=False)
SHOW = typer.Option(False, "--show-config", help="Print the resolved config as YAML and exit.")
MULTIRUN = typer.Option(False, "--multirun", "-m", help="Sweep: one job per combination of comma lists "
                        "(key=a,b), through Hydra's launchers (hydra/launcher=joblib | submitit_slurm); "
                        "summary.csv collects the jobs.")
CONFIG = typer.Option(None, "--config", help="A YAML config to start from (e.g. a run's config or optimize's "
                      "best.yaml); overrides apply on top.", show_default=False)


def describe(defaults, prefix: str = "") -> str:
    """Help text listing a command's config groups and keys with their defaults (``defaults``: the
    command's default config instance), one paragraph per group; the top-level ``fluid`` node (any fluid model:
    simulate's, optimize's) also lists the other models' keys, while a node of one given model
    (validate's ``hydronet``) lists its own."""
    from fishsim.config import FLUID_MODELS

    keys, groups = [], []
    for f in dataclasses.fields(defaults):
        default = getattr(defaults, f.name)
        if not prefix and f.name == "fluid":          # any fluid model: every model's own keys
            groups.append(f"{f.name}: " + describe(default, f.name + "."))
            groups += [f"{f.name}={model}: " + describe(kind(), f.name + ".")
                       for model, kind in FLUID_MODELS.items() if model != default.model]
        elif dataclasses.is_dataclass(default):
            groups.append(f"{prefix}{f.name}: " + describe(default, prefix + f.name + "."))
        else:
            keys.append(f"{prefix}{f.name}={default}")
    if prefix:                                   # a group: its keys, then its sub-groups' keys
        return "  ".join(keys + [g.split(": ", 1)[1] for g in groups])
    return "\n\n".join(["top level: " + "  ".join(keys)] + groups)


class _ConfigHelp(TyperCommand):
    """A command whose epilog, the list of its config keys, is built only when its help is shown:
    building it imports the config dataclasses and OmegaConf, which ``fishsim --help`` and
    ``fishsim --version`` do not need."""

    @property
    def epilog(self) -> str | None:
        if self._epilog is None and self.name is not None:
            from fishsim.config import ROOTS

            self._epilog = "Config (group.key=default):\n\n" + describe(ROOTS[self.name]())
        return self._epilog

    @epilog.setter
    def epilog(self, value: str | None) -> None:
        self._epilog = value


def _on_sigterm(signum, frame) -> None:
    raise Terminated("terminated (SIGTERM)")


_unraisablehook_before = sys.unraisablehook


def _resend_a_dropped_stop(unraisable) -> None:
    """``sys.unraisablehook``: Python drops an exception raised inside a ``__del__`` or a weakref
    callback ("Exception ignored in ..."). A stop signal landing there would be lost and the run go
    on to its end: the signal is sent again, from a thread a moment later so that it lands in the
    running code, not in this hook."""
    import os
    import signal
    import threading

    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        sig = signal.SIGTERM if isinstance(unraisable.exc_value, Terminated) else signal.SIGINT
        threading.Timer(0.01, os.kill, (os.getpid(), sig)).start()
    else:
        _unraisablehook_before(unraisable)


def _handle_stop_signals() -> None:
    """SIGTERM stops a run like SIGINT; SIGINT is handled even when the shell started the command
    in the background with SIGINT ignored, and a stop that Python dropped is sent again."""
    import signal
    import threading

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_sigterm)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        if sys.unraisablehook is not _resend_a_dropped_stop:
            global _unraisablehook_before
            _unraisablehook_before, sys.unraisablehook = sys.unraisablehook, _resend_a_dropped_stop


def _execute(command: str, overrides: list[str] | None, show: bool, run: Callable, config: str | None = None,
             multirun: bool = False) -> None:
    """Compose, validate and run; user errors become one line on stderr and exit code 2;
    Ctrl-C exits 130 and SIGTERM 143, after the command kept its partial results."""
    from fishsim.config import load_config, to_yaml
    from fishsim.io import runrecord
    from fishsim.io.outdir import folders_written, release_locks

    _handle_stop_signals()
    if multirun:
        _sweep(command, list(overrides or []), run, config)
        return
    status = "failed"
    try:
        cfg = load_config(command, overrides, config)
        if show:
            typer.echo(to_yaml(cfg))
            return
        runrecord.begin(command, to_yaml(cfg), list(overrides or []))
        with stops_surface():
            run(cfg)
        status = "complete"
    except FishsimError as err:
        status = f"error: {err}"
        typer.secho(f"error: {err}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2) from None
    except Terminated as err:
        status = "terminated (SIGTERM)"
        typer.secho(f"terminated (SIGTERM): partial results were kept ({err})", fg=typer.colors.YELLOW, err=True)
        raise typer.Exit(code=143) from None
    except KeyboardInterrupt as err:
        status = "interrupted (SIGINT)"
        typer.secho(f"interrupted: partial results were kept ({err})" if str(err) else
                    "interrupted: partial results were kept", fg=typer.colors.YELLOW, err=True)
        raise typer.Exit(code=130) from None
    finally:
        runrecord.end(folders_written(), status)
        release_locks()


def _sweep(command: str, overrides: list[str], run: Callable, config: str | None) -> None:
    """``-m``: a Hydra multirun of ``command`` (fishsim.multirun); one-line errors, exit 2."""
    from fishsim.multirun import sweep

    try:
        if config is not None:
            raise ConfigError("--config and -m do not combine yet: give the sweep's overrides on the command line")
        folder = sweep(command, overrides, run)
    except FishsimError as err:
        typer.secho(f"error: {err}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2) from None
    typer.echo(f"sweep done: {folder}/summary.csv")


def _version(show: bool) -> None:
    if show:
        from fishsim import __version__

        typer.echo(f"fishsim {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                       help="Print fishsim's version and exit.")) -> None:
    """fishsim: a fast, differentiable simulator of soft swimming robots."""


def _positional(args: list[str] | None, keys: tuple[str, ...]) -> list[str]:
    """Bare arguments (no '=') become ``key=value`` for ``keys`` in order (e.g. render's paths)."""
    out, free = [], list(keys)
    for arg in args or []:
        if "=" not in arg and free:
            out.append(f"{free.pop(0)}={arg}")
        else:
            out.append(arg)
    return out


def _command(name: str, summary: str, positional: tuple[str, ...] = ()) -> Callable:
    """Register ``fishsim <name>`` with help text generated from its structured config; bare
    arguments fill the config keys named in ``positional``."""
    def decorate(run_factory: Callable[[], Callable]) -> Callable:
        def command(overrides: list[str] | None = OVERRIDES, show_config: bool = SHOW, config: str = CONFIG,
                    multirun: bool = MULTIRUN) -> None:
            _execute(name, _positional(overrides, positional), show_config, run_factory(), config, multirun)

        command.__doc__ = summary
        app.command(name=name, cls=_ConfigHelp)(command)
        return run_factory

    return decorate


@_command("mesh", "Mesh the fish profile into quality triangles; write the mesh and a preview PNG.")
def _mesh() -> Callable:
    from fishsim.commands.mesh import run

    return run


@_command("simulate", "Simulate B fish swimming (fluid=hydronet | numerical | none); write an HDF5 trajectory.")
def _simulate() -> Callable:
    from fishsim.commands.simulate import run

    return run


@_command("train-hydronet", "Train the HydroNet fluid surrogate on randomised scenes; checkpoints, logs, resume.")
def _train_hydronet() -> Callable:
    from fishsim.commands.train_hydronet import run

    return run


@_command("validate", "Compare against references (suite=hydronet: HydroNet on held-out scenes; suite=solid: mesh convergence, beam theory).")
def _validate() -> Callable:
    from fishsim.commands.validate import run

    return run


@_command("optimize", "Optimise a swimmer's gait or design (adam, any torch.optim, CMA-ES); history, plot, best.yaml.")
def _optimize() -> Callable:
    from fishsim.commands.optimize import run

    return run


@_command("render", "Render a trajectory (or a folder of them): PNG frames, MP4, comparisons, ParaView.",
          positional=("path", "compare"))
def _render() -> Callable:
    from fishsim.render.run import run

    return run


def main() -> None:  # pragma: no cover - console entry point
    sys.exit(app())


if __name__ == "__main__":  # pragma: no cover
    main()
