"""User-facing errors: the CLI prints their message on one line and exits with code 2."""


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
