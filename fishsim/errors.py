"""User-facing errors: the CLI prints their message on one line and exits with code 2."""

from contextlib import contextmanager


class FishsimError(Exception):
    """Base class of errors caused by the user's input, not by a bug; the message says what is
    wrong and how to fix it, in one line."""


class ConfigError(FishsimError):
    """An unknown config key or an impossible value."""


class InputFileError(FishsimError):
    """A missing, corrupt or wrong-kind input file (mesh, model, trajectory)."""


class MeshError(FishsimError):
    """A fish profile or mesh that cannot be simulated (self-intersecting, inverted, degenerate)."""


class SimulationBlowUp(FishsimError):
    """A simulation produced non-finite or runaway values; the message names the step and the
    quantity, and the partial results are kept."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (sent by `timeout`, SLURM, `docker stop`): stops a run like Ctrl-C, outputs kept;
    the CLI exits 143 (Ctrl-C: 130)."""


@contextmanager
def stops_surface():
    """Re-raise a stop signal that compiled code wrapped: a SIGINT or SIGTERM landing while numba
    code calls back into Python (e.g. to unpickle a constant) surfaces as a SystemError ("returned
    a result with an exception set") caused by the KeyboardInterrupt or Terminated; inside this
    context that stop is raised instead, so a run stops as a stop (exit 130 / 143, partial results
    kept), not as a crash. Other errors pass unchanged."""
    try:
        yield
    except SystemError as err:
        stop = err
        while stop is not None and not isinstance(stop, KeyboardInterrupt):
            stop = stop.__cause__ or stop.__context__
        if stop is None:
            raise
        raise stop from None
