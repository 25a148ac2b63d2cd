"""Frame pictures: size, content, the fish where the trajectory puts it, fixed colour limits."""

import h5py
import numpy as np
import pytest

from fishsim.errors import InputFileError
from fishsim.render.config import RenderConfig
from fishsim.render.data import load_render_data
from fishsim.render.fields import colour_limits, vorticity
from fishsim.render.scene import FrameFigure, follow_limits, follow_window
from fishsim.render.synthetic import write_synthetic_trajectory


def _figure(path, **kw):
    data = load_render_data(path)
    return data, FrameFigure([data], RenderConfig(path=str(path), width=480, **kw))


def _is_fish(rgb: np.ndarray) -> np.ndarray:
    """Dark grey (face 0.3, edges 0.08): no colour map of the renderer has such pixels."""
    rgb = rgb.astype(int)
    return (rgb.max(-1) - rgb.min(-1) < 20) & (rgb.max(-1) < 110)


def _pixels(fig, rgb, xy):
    cr = np.round(fig.data_to_pixel(0, xy)).astype(int)
    return rgb[cr[:, 1], cr[:, 0]]


def test_frame_size_and_content(traj):
    data, fig = _figure(traj)
    fig.update(4)
    rgb = fig.rgb()
    assert rgb.shape == (fig.size[1], fig.size[0], 3)
    assert fig.size[0] == 480 and fig.size[1] % 16 == 0
    x0, x1, y0, y1 = data.extent()
    ph = fig.panels[0].ax.get_window_extent()
    assert ph.height / ph.width == pytest.approx((y1 - y0) / (x1 - x0), rel=0.02)  # equal x/y scale
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 200                           # not blank
    assert ((rgb[..., 0] > 200) & (rgb[..., 1] < 60) & (rgb[..., 2] < 60)).sum() > 20  # red arrows


def test_fish_is_drawn_where_the_trajectory_says(traj):
    data, fig = _figure(traj)
    images = {}
    for t in (0, data.n_frames - 1):
        fig.update(t)
        images[t] = fig.rgb()
    last = data.n_frames - 1
    for t, away in ((0, last), (last, 0)):
        inside = data.q[t][data.triangles].mean(axis=1)        # triangle centroids, near the outline too
        assert _is_fish(_pixels(fig, images[t], inside)).mean() > 0.9
        # the same pixels when the fish has swum elsewhere show the fluid, not the fish
        assert _is_fish(_pixels(fig, images[away], inside)).mean() < 0.05
    # just outside the outline (2 node spacings away from the body, above and below): no fish
    c = data.q[last].mean(axis=0)
    outside = c + np.array([[0, 0.15 * data.fish_length + 3 * data.grid[2]], [0, -0.15 * data.fish_length - 3 * data.grid[2]]])
    assert not _is_fish(_pixels(fig, images[last], outside)).any()


def test_colour_limits_are_robust_fixed_and_shown(traj):
    data, fig = _figure(traj)
    fluid = data.fluid["mask"] < 0.5
    top = np.percentile(np.abs(data.fluid["p"][fluid]), 99)
    assert fig.clim == pytest.approx((-top, top))
    assert fig.colorbar.mappable.get_clim() == pytest.approx((-top, top))
    for t in (0, 5, 11):
        fig.update(t)
        assert fig.panels[0].image.get_clim() == pytest.approx((-top, top))
    _, speed = _figure(traj, field="speed")
    assert speed.clim[0] == 0 and speed.clim[1] > 0


def test_latest_stored_fluid_frame_is_shown(traj):
    data, fig = _figure(traj)
    fig.update(5)                                   # fluid stored at 0, 2, 4, ...
    np.testing.assert_array_equal(fig.panels[0].image.get_array(), data.fluid["p"][2])
    assert "fluid of frame 4" in fig.panels[0].stamp.get_text()
    assert data.fluid_index(5) == 2 and data.fluid_index(4) == 2


def test_vorticity_of_solid_body_rotation_is_twice_the_rate():
    dx, omega = 0.01, 3.0
    y, x = np.mgrid[0:8, 0:10] * dx
    np.testing.assert_allclose(vorticity(-omega * y, omega * x, dx), 2 * omega)
    assert colour_limits(np.array([[[-1.0, 4.0]]]), "vorticity", 100) == (-4.0, 4.0)


def test_follow_window_tracks_the_centroid(traj):
    data, fig = _figure(traj, follow=True)
    w, h = follow_window(data, 0.0)
    assert w == pytest.approx(min(3 * data.fish_length, data.extent()[1]))
    for t in (3, 9):
        fig.update(t)
        xlim = fig.panels[0].ax.get_xlim()
        assert xlim[1] - xlim[0] == pytest.approx(w)
        assert xlim[0] < data.q[t, :, 0].mean() < xlim[1]
        assert xlim == pytest.approx(follow_limits(data, t, (w, h))[0])


def test_vacuum_run_draws_the_fish_only(tmp_path):
    path = write_synthetic_trajectory(tmp_path / "vac.h5", n_frames=4, fluid=False)
    data, fig = _figure(path)
    assert not data.has_fluid and fig.colorbar is None and "no fluid" in fig.title
    fig.update(2)
    rgb = fig.rgb()
    assert _is_fish(_pixels(fig, rgb, data.q[2][data.triangles].mean(axis=1))).mean() > 0.9


def test_batch_sample_and_grid_inference(tmp_path, other):
    path = write_synthetic_trajectory(tmp_path / "batch.h5", n_frames=3, batch=2)
    data = load_render_data(path, sample=1)
    with h5py.File(path) as f:
        np.testing.assert_array_equal(data.q, f["solid/q"][:, 1])
        np.testing.assert_array_equal(data.fluid["p"], f["fluid/p"][:, 1])
    with pytest.raises(InputFileError, match="sample=2 does not exist"):
        load_render_data(path, sample=2)
    inferred = load_render_data(other)                       # no grid_* attributes in this file
    assert inferred.grid == (20, 60, pytest.approx(2.5e-3))
    assert inferred.extent() == pytest.approx((0, 0.15, 0, 0.05))


def test_normalised_frames_use_unit_limits(traj):
    _, fig = _figure(traj, normalize=True)
    assert fig.clim == (-1.0, 1.0)
    assert np.abs(fig.panels[0].frames).max(axis=(1, 2)) == pytest.approx(1.0)
