"""Force arrows: thinned to about arrow_count, each the total force on its stretch of surface."""

import numpy as np


def test_arrows_are_thinned_and_add_up_to_the_total_force():
    from fishsim.render.fields import arrow_forces

    rng = np.random.default_rng(0)
    f_ext = rng.normal(size=(3, 250, 2))
    surface = np.arange(10, 228)                           # 218 surface nodes, as the default fish
    anchor, forces = arrow_forces(f_ext, surface, 40)
    assert 35 <= len(anchor) <= 40 and np.all(np.isin(anchor, surface))
    np.testing.assert_allclose(forces.sum(1), f_ext[:, surface].sum(1), rtol=1e-12)
    anchor, forces = arrow_forces(f_ext, surface, 0)       # one arrow per node
    np.testing.assert_array_equal(anchor, surface)
    np.testing.assert_array_equal(forces, f_ext[:, surface])
