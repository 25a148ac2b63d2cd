"""Differentiable solid-fluid coupling (paper Sec. 3.3, docs/physics.md section 7).

solid -> fluid: ``soft_mask`` (b), ``boundary_velocity`` (v_d), on a band of cells around the body;
``band_boundary`` both at once (compiled on the CPU), ``band_values`` on the band's cells only.
fluid -> solid: ``ibm_force`` (pressure forces on surface nodes) or ``spread_to_surface`` (the
numerical fluid's momentum exchange, exchange.py), ``fext_from_surface`` (modes, x-axis fixing,
burn-in).  ``solid_to_fluid`` (``with_walls``: united with the tank's walls) / ``fluid_to_solid`` /
``exchange_to_solid`` do each direction in one call from a ``CouplingConfig``.  added_mass.py: the stabilisation of the explicit coupling.
"""

from fishsim.lazy import exports

__getattr__, __all__ = exports(__name__, {
    "band": ("SurfaceBand", "band_margin", "surface_band"),
    "config": ("CouplingConfig",),
    "exchange": ("spread_to_surface",),
    "forces": ("burn_in_scale", "fext_from_surface"),
    "geometry": ("area_vectors", "polygon_area", "surface_geometry"),
    "ibm": ("ibm_force", "surface_pressure"),
    "layer": ("exchange_to_solid", "fish_band", "fluid_to_solid", "on_grid", "solid_to_fluid", "united_with_nothing",
              "with_walls"),
    "mask": ("band_boundary", "band_values", "boundary_velocity", "soft_distance", "soft_mask"),
})
