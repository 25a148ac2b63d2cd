"""Differentiable solid-fluid coupling (paper Sec. 3.3, docs/physics.md section 7).

solid -> fluid: ``soft_mask`` (b), ``boundary_velocity`` (v_d), on a band of cells around the body.
fluid -> solid: ``ibm_force`` (pressure forces on surface nodes) or ``spread_to_surface`` (the
numerical fluid's momentum exchange, exchange.py), ``fext_from_surface`` (modes, x-axis fixing,
burn-in).  ``solid_to_fluid`` / ``fluid_to_solid`` / ``exchange_to_solid`` do each direction in
one call from a ``CouplingConfig``.  added_mass.py: the stabilisation of the explicit coupling.
"""

from fishsim.coupling.band import SurfaceBand, band_margin, surface_band
from fishsim.coupling.exchange import spread_to_surface
from fishsim.coupling.forces import burn_in_scale, fext_from_surface
from fishsim.coupling.geometry import area_vectors, polygon_area, surface_geometry
from fishsim.coupling.ibm import ibm_force, surface_pressure
from fishsim.coupling.layer import CouplingConfig, exchange_to_solid, fluid_to_solid, solid_to_fluid
from fishsim.coupling.mask import boundary_velocity, soft_distance, soft_mask

__all__ = [
    "CouplingConfig", "SurfaceBand", "area_vectors", "band_margin", "boundary_velocity",
    "burn_in_scale", "exchange_to_solid", "fext_from_surface", "fluid_to_solid", "ibm_force",
    "polygon_area", "soft_distance", "soft_mask", "solid_to_fluid", "spread_to_surface",
    "surface_band", "surface_geometry", "surface_pressure",
]
