"""``fishsim mesh``: mesh the fish profile, write the mesh file and a preview picture.

The mesh file always carries the mesher's actuator stations (the paper's muscles, used by
``fish.muscles=paper``); with the default ``fish.muscles=layer`` it also carries the layer's
area fractions per element (muscle_top, muscle_bottom) and the preview shows the layer, the
muscles a simulation with this config uses.
"""

from __future__ import annotations

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from fishsim.config import MeshCommandConfig
from fishsim.episode import build_fish_mesh
from fishsim.io.outdir import make_out_dir, output_file


def run(cfg: MeshCommandConfig) -> dict:
    """Mesh, write, preview; print and return the mesh statistics."""
    from fishsim.io.mesh_io import write_mesh
    from fishsim.mesh import mesh_quality
    from fishsim.render.mesh_preview import plot_mesh

    out_dir = make_out_dir("mesh", cfg.out_dir)
    mesh_path = output_file(out_dir, cfg.output, "fish.vtu")
    fish = cfg.fish
    mesh = build_fish_mesh(fish)
    quality = mesh_quality(mesh)
    stats = {"nodes": mesh.n_nodes, "elements": mesh.n_elements, "surface nodes": len(mesh.surface)}
    layer, fractions = None, None
    if fish.muscles == "layer":
        import torch

        from fishsim.solid.muscles import layer_fractions

        layer = (fish.muscle_thickness, tuple(fish.actuator_x_range))
        f_top, f_bot = (f.numpy() for f in layer_fractions(mesh, torch.tensor(float(fish.muscle_thickness)),
                                                            layer[1]))
        fractions = {"muscle_top": f_top, "muscle_bottom": f_bot}
        stats["muscle layer (top)"] = f"{int((f_top > 1e-9).sum())} elements"
        stats["muscle layer (bottom)"] = f"{int((f_bot > 1e-9).sum())} elements"
        stats["muscle layer thickness"] = f"{fish.muscle_thickness:g} of the local half-width"
    else:
        stats["actuated (top)"] = int((mesh.actuator == 1).sum())
        stats["actuated (bottom)"] = int((mesh.actuator == 2).sum())
    write_mesh(mesh, mesh_path, cell_data=fractions)
    stats["min angle [deg]"] = round(float(quality["min_angle"]), 2)
    stats["mesh"] = str(mesh_path)
    if cfg.preview:
        preview = mesh_path.with_suffix(".png")
        muscles = "paper's muscle stations" if layer is None else (
            f"muscle layer {layer[0]:g} of the half-width, X in [{layer[1][0]:g}, {layer[1][1]:g}] L "
            "(shade: area fraction)")
        plot_mesh(mesh, preview, title=f"fish mesh, L = {mesh.length} m, {muscles}", layer=layer)
        stats["preview"] = str(preview)
    _print(stats)
    return stats


def _print(stats: dict) -> None:
    table = Table(title="fishsim mesh", show_header=False)
    for k, v in stats.items():
        table.add_row(escape(k), escape(str(v)))
    Console().print(table)
