"""Passive validation of the PD solid against Euler-Bernoulli beam theory (fishsim/solid/beam.py):
a clamped 100 x 5 mm cantilever of the fish's material, refined through 2, 4 and 8 elements
across its thickness. Measured (1 mm tip deflection): static error -24.1 / -7.5 / -1.9 %
(second order: linear triangles are stiff in bending), first bending frequency +17.9 / +4.5 /
+1.5 % (h = 2 ms, implicit Euler's period error removed); 16 across: static -0.4 %."""

import pytest

from fishsim.solid.beam import Cantilever, plane_modulus
from fishsim.solid.config import SolidMaterial


def _beam(volume_term=False):
    beam = Cantilever(material=SolidMaterial(volume_term=volume_term))
    load = 3 * beam.bending_stiffness * 1e-3 / beam.length**3               # 1 mm tip deflection
    return beam, load


def test_plane_modulus_of_the_fish_material():
    assert plane_modulus(SolidMaterial()) == pytest.approx(6e5 / 1.45)            # 2 mu_s, lambda' = 0
    assert plane_modulus(SolidMaterial(volume_term=True)) == pytest.approx(700_262, rel=1e-5)


@pytest.mark.parametrize("volume_term", [False, True])
def test_static_tip_deflection_converges_to_euler_bernoulli(volume_term):
    beam, load = _beam(volume_term)
    exact = beam.tip_deflection(load)
    errors = [beam.static_deflection(beam.thickness / n, load)[0] / exact - 1 for n in (2, 4, 8)]
    assert errors[0] < errors[1] < errors[2] < 0                      # too stiff, less so when refined
    assert abs(errors[1]) > 3 * abs(errors[2])                         # second order in the element size
    assert abs(errors[2]) < 0.025
    richardson = errors[2] + (errors[2] - errors[1]) / 3               # extrapolated to zero element size
    assert abs(richardson) < 0.005


def test_first_bending_frequency_converges_to_euler_bernoulli():
    beam, load = _beam()
    exact = beam.first_frequency()
    assert exact == pytest.approx(5.196, rel=1e-3)
    coarse, fine = (beam.vibration_frequency(beam.thickness / n, load, periods=1.6) / exact - 1 for n in (2, 4))
    assert coarse > fine > 0 and coarse > 3 * fine and fine < 0.05
