"""The fish mesh: profile w(X), triangulation, surface polyline and actuator groups."""

from fishsim.mesh.fish_mesh import ACTUATOR_BOTTOM, ACTUATOR_NONE, ACTUATOR_TOP, FishMesh
from fishsim.mesh.profile import (
    DEFAULT_POLY_COEFFS,
    Profile,
    check_outline,
    check_profile,
    kern_profile,
    make_profile,
    polynomial_profile,
)
from fishsim.mesh.triangulate import (
    boundary_edges,
    check_mesh,
    element_angles,
    element_areas,
    make_fish_mesh,
    mesh_quality,
    surface_elements,
    surface_polyline,
)

__all__ = [
    "ACTUATOR_BOTTOM",
    "ACTUATOR_NONE",
    "ACTUATOR_TOP",
    "DEFAULT_POLY_COEFFS",
    "FishMesh",
    "Profile",
    "boundary_edges",
    "check_mesh",
    "check_outline",
    "check_profile",
    "element_angles",
    "element_areas",
    "kern_profile",
    "make_fish_mesh",
    "make_profile",
    "mesh_quality",
    "polynomial_profile",
    "surface_elements",
    "surface_polyline",
]
