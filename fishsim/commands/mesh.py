"""``fishsim mesh``: mesh the fish profile, write the mesh file and a preview picture."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table

from fishsim.config import FishConfig, MeshCommandConfig
from fishsim.io.outdir import make_out_dir, resolve_output


def build_fish_mesh(fish: FishConfig):
    """The fish mesh a config asks for: read from ``fish.mesh_file`` or generated."""
    from fishsim.io.mesh_io import read_mesh
    from fishsim.mesh import make_fish_mesh

    if fish.mesh_file:
        return read_mesh(fish.mesh_file)
    return make_fish_mesh(
        length=fish.length,
        profile=fish.profile,
        poly_coeffs=list(fish.poly_coeffs) or None,
        edge_length=fish.edge_length,
        min_angle=fish.min_angle,
        actuator_spacing=fish.actuator_spacing,
        actuator_x_range=tuple(fish.actuator_x_range),
        tail_tip_width=fish.tail_tip_width,
    )


def build_muscles(fish: FishConfig, mesh):
    """The muscle layout a config asks for (fishsim.solid.muscles): ``fish.muscles=layer`` (the
    default, a layer of ``fish.muscle_thickness`` times the local half-width along each side within
    ``fish.actuator_x_range``) or ``paper`` (the mesher's stations)."""
    from fishsim.solid.muscles import layer_muscles, station_muscles

    if fish.muscles == "paper":
        return station_muscles(mesh)
    return layer_muscles(mesh, fish.muscle_thickness, tuple(fish.actuator_x_range))


def run(cfg: MeshCommandConfig) -> dict:
    """Mesh, write, preview; print and return the mesh statistics."""
    from fishsim.io.mesh_io import write_mesh
    from fishsim.mesh import mesh_quality
    from fishsim.render.mesh_preview import plot_mesh

    out_dir = make_out_dir("mesh", cfg.out_dir)
    mesh = build_fish_mesh(cfg.fish)
    quality = mesh_quality(mesh)
    mesh_path = resolve_output(out_dir, cfg.output)
    write_mesh(mesh, mesh_path)
    stats = {
        "nodes": mesh.n_nodes,
        "elements": mesh.n_elements,
        "surface nodes": len(mesh.surface),
        "actuated (top)": int((mesh.actuator == 1).sum()),
        "actuated (bottom)": int((mesh.actuator == 2).sum()),
        "min angle [deg]": round(float(quality["min_angle"]), 2),
        "mesh": str(mesh_path),
    }
    if cfg.preview:
        preview = mesh_path.with_suffix(".png")
        plot_mesh(mesh, preview, title=f"fish mesh, L = {mesh.length} m")
        stats["preview"] = str(preview)
    _print(stats)
    return stats


def _print(stats: dict) -> None:
    table = Table(title="fishsim mesh", show_header=False)
    for k, v in stats.items():
        table.add_row(k, str(v))
    Console().print(table)
