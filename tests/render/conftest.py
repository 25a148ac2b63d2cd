"""Small synthetic trajectories (a fish crossing a 20 x 60 grid) shared by the render tests."""

import pytest

from fishsim.render.synthetic import write_synthetic_trajectory


@pytest.fixture(scope="session")
def traj(tmp_path_factory):
    """12 frames, fluid stored every 2nd frame, grid attributes present."""
    return write_synthetic_trajectory(tmp_path_factory.mktemp("traj") / "fish.h5", n_frames=12)


@pytest.fixture(scope="session")
def other(tmp_path_factory):
    """A second run (shorter fish, no grid attributes: grid inferred from the fluid arrays)."""
    return write_synthetic_trajectory(tmp_path_factory.mktemp("other") / "other.h5", n_frames=12,
                                      length=0.04, grid_attrs=False)
