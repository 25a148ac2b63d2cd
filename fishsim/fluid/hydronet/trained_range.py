"""The fluid a HydroNet was trained for, and the check that a run stays inside it.

A HydroNet learns one fluid (or a range of them with ``net.condition``), on one cell size and
one time step: outside them its steps are extrapolated and can be far off (the shipped model at
rho = 1000, mu = 1e-3: a 34 % one-step error) without any sign in the output. So every model
file carries its ``training_range`` (rho and mu ranges, dx, h; written by ``save_weights`` and
``export_model``, or for an older file in the ``.json`` metadata beside it), and a run outside
it warns in one line, or is refused when the config asks for that (``fluid.strict_range``;
``fishsim validate``: ``hydronet.strict_range``).
"""

from __future__ import annotations

import json
from pathlib import Path

from fishsim.errors import ConfigError

RTOL = 1e-6   # float32 round trips of dx = 2.5e-3 and friends are "equal"


def training_range(pool) -> dict:
    """{rho: [lo, hi], mu: [lo, hi], dx, h, scene_cells: [H, W]} of a PoolConfig (or its dict, as
    stored in a checkpoint): the fluid, and the size of the scenes (their channel flows included)."""
    get = (lambda k: pool[k]) if isinstance(pool, dict) else (lambda k: getattr(pool, k))
    return {"rho": [float(v) for v in get("rho")], "mu": [float(v) for v in get("mu")],
            "dx": float(get("dx")), "h": float(get("h")), "scene_cells": [int(get("H")), int(get("W"))]}


def stored_range(data: dict, path: Path) -> dict | None:
    """The training range of a loaded model file: its own entry, that of a checkpoint's config,
    or the ``training_range`` of the ``.json`` metadata beside it; None if none is known. A range
    stored before the scenes' size was (no ``scene_cells``) takes it from the metadata's pool."""
    if "training_range" in data:
        found = data["training_range"]
    elif isinstance(data.get("config"), dict) and "pool" in data["config"]:
        found = training_range(data["config"]["pool"])
    else:
        found = _metadata(path).get("training_range")
    if found is not None and "scene_cells" not in found:
        pool = _metadata(path).get("train_config", {}).get("pool", {})
        if "H" in pool and "W" in pool:
            found = {**found, "scene_cells": [int(pool["H"]), int(pool["W"])]}
    return found


def _metadata(path: Path) -> dict:
    """The ``.json`` metadata beside a model file ({} if none or unreadable)."""
    meta = Path(path).with_suffix(".json")
    try:
        return json.loads(meta.read_text()) if meta.is_file() else {}
    except (OSError, ValueError):
        return {}


def outside(trained: dict, rho: float, mu: float, dx: float, h: float) -> list[str]:
    """What of (rho, mu, dx, h) lies outside ``trained``, as 'name = value' strings."""
    checks = [("rho", rho, *trained["rho"]), ("mu", mu, *trained["mu"]),
              ("dx", dx, trained["dx"], trained["dx"]), ("h", h, trained["h"], trained["h"])]
    return [f"{name} = {v:g}" for name, v, lo, hi in checks if not lo * (1 - RTOL) <= v <= hi * (1 + RTOL)]


def describe(trained: dict) -> str:
    """'rho in [50, 50] kg/m^3, mu in [0.000125, 0.000125] Pa s, dx = 0.0025 m, h = 0.01 s'."""
    (r0, r1), (m0, m1) = trained["rho"], trained["mu"]
    return (f"rho in [{r0:g}, {r1:g}] kg/m^3, mu in [{m0:g}, {m1:g}] Pa s, dx = {trained['dx']:g} m, "
            f"h = {trained['h']:g} s")


def check_fluid(model, path, rho: float, mu: float, dx: float, h: float, strict: bool,
                key: str = "fluid") -> str | None:
    """Warn (one line on stderr) or, when ``strict``, raise ConfigError if (rho, mu, dx, h) is
    outside the range the HydroNet ``model`` (loaded from ``path``) was trained for; returns the
    message (None inside the range, or for a model whose range is unknown). ``key``: the config
    node of the model, whose ``strict_range`` the message names (``fishsim validate``: hydronet)."""
    trained = getattr(model, "training_range", None)
    wrong = outside(trained, rho, mu, dx, h) if trained else []
    if not wrong:
        return None
    message = (f"HydroNet {path} was trained for {describe(trained)}; this run has {', '.join(wrong)}, outside "
               f"that range, so its fluid is extrapolated and can be far off: use fluid=numerical, or a model "
               f"trained for it (fishsim train-hydronet pool.rho=[{rho:g},{rho:g}] pool.mu=[{mu:g},{mu:g}] "
               f"pool.dx={dx:g} pool.h={h:g})")
    return _warn_or_refuse(message, strict, key)


def check_channel(model, path, tank_cells: int, strict: bool, key: str = "fluid") -> str | None:
    """Warn (one line on stderr) or, when ``strict``, raise ConfigError for a channel flow (the
    swim tunnel or a tank inflow) through a tank of ``tank_cells`` cells along the flow, longer
    than the scenes the HydroNet ``model`` learned channel flows on: there the flow entering one end
    does not cross the tank (the shipped model, 64 x 128-cell scenes, in the paper's 300-cell tank
    at 60 frames: the flux across its middle 0 % of the tunnel's, at its ends 14-16 %, where it
    leaves through the side walls; the tunnel's fish, which then feels no oncoming water, swims
    1.7-2.1x as far as in still water at 3-7 Hz against 0.99-1.02x with the numerical fluid).
    Returns the message (None when the tank is no longer than the scenes or their size is
    unknown)."""
    trained = getattr(model, "training_range", None) or {}
    scene = trained.get("scene_cells")
    if not scene or tank_cells <= scene[1]:
        return None
    message = (f"HydroNet {path} learned channel flows on scenes of {scene[0]} x {scene[1]} cells; through this "
               f"{tank_cells}-cell tank its flow does not cross (the shipped model's swim tunnel: no flux across the "
               f"tank's middle, a fish 1.7-2.1x as fast as in still water): use fluid=numerical for the swim tunnel "
               f"and inflows, or a model trained on scenes as long as the tank (fishsim train-hydronet "
               f"pool.W={tank_cells})")
    return _warn_or_refuse(message, strict, key)


def _warn_or_refuse(message: str, strict: bool, key: str) -> str:
    """Raise ConfigError with ``message`` when ``strict`` (``{key}.strict_range``), else print it
    as a one-line warning on stderr; returns it."""
    if strict:
        raise ConfigError(message + f"; {key}.strict_range=true refuses it")
    from rich.console import Console
    from rich.markup import escape

    Console(stderr=True, soft_wrap=True).print(f"[yellow]warning: {escape(message)} ({key}.strict_range=true "
                                               "refuses such runs)[/]")
    return message
