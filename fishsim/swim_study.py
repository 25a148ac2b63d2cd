"""The paper's frequency study (Fig. 4): the head's x displacement after an episode against the
controller frequency, for several fluids, each batched (B = number of frequencies) in one rollout,
compared with a reference fluid (the numerical solver on the refined grid by default).

Per fluid: displacement [mm] per frequency, the lateral drift [mm] (the mass centroid's y
displacement: a fish that turns), wall time, and against the reference the Spearman rank
correlation rho_s (Pearson correlation of the ranks), the argmax frequency, and the mean absolute
mismatch in mm and in grid cells (dx). A fish that blows up is marked (NaN, its frame and reason)
and the rest of its batch carries on.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from fishsim.errors import ConfigError
from fishsim.swim_study_config import FLUIDS, ConvergenceStudyConfig, SwimStudyConfig

# The paper's Table 1 (300 frames, their hardware) and Fig. 4 (mean mismatch, argmax).
PAPER = {"hydronet_forward_s_per_frame": 213.0 / 300, "comsol_s_per_frame": (5 * 3600 + 16 * 60 + 39) / 300,
         "mean_mismatch_mm": 15.0, "mean_mismatch_cells": 6.0, "argmax_hz": 5.0}


def spearman(a, b) -> float:
    """Spearman rank correlation of two sequences over the entries finite in both (a fish that
    blew up in either fluid is left out); NaN with fewer than two such entries or if either is
    constant on them."""
    from scipy.stats import spearmanr

    a, b = np.asarray(a, float), np.asarray(b, float)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    if len(a) < 2 or a.std() == 0 or b.std() == 0:
        return math.nan
    return float(spearmanr(a, b).statistic)


def run_fluid(name: str, cfg: SwimStudyConfig, device: str = "cpu") -> dict:
    """One batched episode of every frequency in fluid ``name`` (``episode``)."""
    model = cfg.hydronet_overrides if "fluid=hydronet" in FLUIDS[name] else []
    return episode([*FLUIDS[name], *cfg.overrides, *model], cfg.frequencies, cfg.frames, device)


def episode(overrides: list[str], frequencies, frames: int, device: str = "cpu") -> dict:
    """One batched `fishsim simulate` episode (B = one fish per frequency, in memory, no files)
    with ``overrides``: the head's x displacement [mm], the centroid's y displacement (lateral
    drift) [mm] and the mean thrust F_x [mN/m] per fish, the wall time and any fish that blew up
    (NaN, with its frame and reason)."""
    from fishsim.config import load_config
    from fishsim.coupling.added_mass import mass_centroid
    from fishsim.episode import build_episode
    from fishsim.rollout import head_node, rollout

    freqs = ",".join(str(f) for f in frequencies)
    sim = load_config("simulate", [*overrides, f"frames={frames}", f"batch.frequency=[{freqs}]", f"device={device}"])
    ep = build_episode(sim)
    state = ep.swimmer.initial_state(ep.params, ep.origin)
    head0 = state.q[:, head_node(ep.swimmer.solid.mesh), 0].clone()
    y0 = mass_centroid(state.q, ep.swimmer.node_mass(state.q))[:, 0, 1].clone()
    failures: dict = {}
    t0 = time.perf_counter()
    with torch.no_grad():
        _, m = rollout(ep.swimmer, state, ep.params, sim.frames, failures=failures)
    wall = time.perf_counter() - t0
    dx_mm = (1e3 * (m["head_x"][-1] - head0)).cpu().numpy()
    drift_mm = (1e3 * (m["centroid_y"][-1] - y0)).cpu().numpy()
    thrust = (1e3 * m["thrust_x"].mean(0)).cpu().numpy()
    for b in failures:
        dx_mm[b] = drift_mm[b] = thrust[b] = math.nan
    return {"displacement_mm": dx_mm.tolist(), "lateral_drift_mm": drift_mm.tolist(),
            "mean_thrust_mN": thrust.tolist(), "wall_s": wall,
            "dx_mm": 1e3 * sim.tank.dx, "s_per_fish_frame": wall / (len(frequencies) * sim.frames),
            "failures": {str(frequencies[b]): {"frame": f, "reason": why} for b, (f, why) in failures.items()}}


def compare(result: dict, reference: dict, frequencies) -> dict:
    """rho_s, argmax and the mean absolute mismatch of ``result`` against ``reference``."""
    a, r = np.asarray(result["displacement_mm"]), np.asarray(reference["displacement_mm"])
    ok = np.isfinite(a) & np.isfinite(r)
    mismatch = float(np.mean(np.abs(a[ok] - r[ok]))) if ok.any() else math.nan
    f = np.asarray(frequencies, float)
    return {"spearman": spearman(a, r),
            "argmax_hz": float(f[np.nanargmax(a)]) if np.isfinite(a).any() else math.nan,
            "mean_mismatch_mm": mismatch, "mean_mismatch_cells": mismatch / result["dx_mm"]}


def reusable(cfg: SwimStudyConfig) -> dict:
    """The fluids of ``cfg.reuse`` (an earlier study's metrics.json) this study takes as they are,
    each marked ``reused_from``: every fluid of the stored study if its frequencies, frames and
    overrides are this one's (else a ConfigError: its numbers answer another question), less the
    HydroNet fluids whose hydronet_overrides differ (another model). {} without reuse."""
    if not cfg.reuse:
        return {}
    path = Path(cfg.reuse)
    try:
        stored = json.loads(path.read_text())
        study, fluids = stored["swim"], stored["fluids"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ConfigError(f"swim.reuse={path}: not the metrics.json of a `fishsim validate suite=swim` run "
                          f"({type(e).__name__}: {e})") from e
    for key in ("frequencies", "frames", "overrides"):
        if study.get(key) != getattr(cfg, key):
            raise ConfigError(f"swim.reuse={path}: that study ran with {key}={study.get(key)}, this one with "
                              f"{getattr(cfg, key)}; reuse a study with the same frequencies, frames and overrides")
    same_model = study.get("hydronet_overrides") == cfg.hydronet_overrides
    return {name: {**res, "reused_from": str(path)} for name, res in fluids.items()
            if name in FLUIDS and (same_model or "fluid=hydronet" not in FLUIDS[name])}


def frequency_study(cfg: SwimStudyConfig, device: str = "cpu",
                    progress: Callable[[str], None] | None = None) -> dict:
    """Every fluid of ``cfg`` (reference first), compared with the reference; those ``reusable``
    from ``cfg.reuse`` are read, not re-run."""
    order = [cfg.reference] + [f for f in cfg.fluids if f != cfg.reference]
    stored = reusable(cfg)
    results = {}
    for name in order:
        if progress:
            progress(name)
        results[name] = stored[name] if name in stored else run_fluid(name, cfg, device)
    for name, res in results.items():
        res.update(compare(res, results[cfg.reference], cfg.frequencies))
    return results


# ------------------------------------------------------------------------------------------------
# Convergence of the study in the numerical knobs (suite=convergence)
# ------------------------------------------------------------------------------------------------


MIN_RICHARDSON_ORDER = 0.5
"""The lowest observed order a Richardson estimate is given for: below it e2 / (r^p - 1)
extrapolates the last change more than 2.4-fold (14-fold at p = 0.1), so the sequence is not
in its asymptotic range and the estimate would mean nothing."""


def observed_order(values, d) -> dict:
    """From results d at settings ``values`` (coarse to fine, constant ratio r), the observed
    order p = ln(e1 / e2) / ln r of the last three (e1 = d2 - d1, e2 = d3 - d2; NaN unless they
    converge monotonically) and the Richardson estimate d_inf = d3 + e2 / (r^p - 1) (NaN below
    ``MIN_RICHARDSON_ORDER``); with two settings only the last change. All per column of d
    [n_values, n]."""
    d = np.asarray(d, float)
    v = np.asarray(values, float)
    last_change = d[-1] - d[-2]
    out = {"last_change": last_change.tolist(), "order": [math.nan] * d.shape[1], "richardson": [math.nan] * d.shape[1]}
    if len(v) < 3:
        return out
    r = max(v[-1] / v[-2], v[-2] / v[-1])
    e1, e2 = d[-2] - d[-3], d[-1] - d[-2]
    for j in range(d.shape[1]):
        if e1[j] * e2[j] > 0 and abs(e2[j]) < abs(e1[j]):
            p = math.log(abs(e1[j] / e2[j])) / math.log(r)
            out["order"][j] = p
            if p >= MIN_RICHARDSON_ORDER:
                out["richardson"][j] = float(d[-1, j] + e2[j] / (r ** p - 1))
    return out


def convergence_study(cfg: ConvergenceStudyConfig, device: str = "cpu",
                      progress: Callable[[str], None] | None = None) -> dict:
    """Each knob's settings run as one batched episode (runs of the same resolved config shared,
    e.g. every knob's default, or a limit that is another knob's setting); per knob the
    displacement and thrust per setting, their observed orders, Richardson estimates and the
    default's error against the finest setting and against the Richardson estimate; for a knob
    with a ``limit``, that run ("limit": its overrides, displacement, thrust, wall time; run after
    the knob's ``base``, listed as "base") and the default's error against it."""
    from fishsim.config import load_config

    cache: dict[str, dict] = {}

    def run(what: str, overrides: list[str], frames: int) -> dict:
        key = repr(load_config("simulate", [*cfg.overrides, *overrides, f"frames={frames}"]))
        if key not in cache:
            if progress:
                progress(what)
            cache[key] = episode([*cfg.overrides, *overrides], cfg.frequencies, frames, device)
        return cache[key]

    results = {}
    for name, knob in cfg.knobs.items():
        frames = knob.frames or cfg.frames
        lengths = [knob.episode_frames(v, frames) for v in knob.values]
        runs = [run(f"{name} {knob.override(v)}", [*knob.base, knob.override(v)], n)
                for v, n in zip(knob.values, lengths)]
        d = np.array([r["displacement_mm"] for r in runs])
        f = np.array([r["mean_thrust_mN"] for r in runs])
        entry = {"key": knob.key, "values": list(knob.values), "default": knob.default, "base": list(knob.base),
                 "frames": frames,
                 "episode_frames": lengths,
                 "displacement_mm": d.tolist(), "mean_thrust_mN": f.tolist(),
                 "wall_s": [r["wall_s"] for r in runs], "failures": [r["failures"] for r in runs],
                 "displacement": observed_order(knob.values, d), "thrust": observed_order(knob.values, f)}
        i = list(knob.values).index(knob.default) if knob.default in knob.values else None
        if i is not None:
            rich = np.asarray(entry["displacement"]["richardson"])
            entry["default_error_vs_finest"] = ((d[i] - d[-1]) / np.abs(d[-1])).tolist()
            entry["default_error_vs_richardson"] = ((d[i] - rich) / np.abs(rich)).tolist()
        if knob.limit:
            limit = [*knob.base, *knob.limit]
            lim = run(f"{name} limit {' '.join(limit)}", limit, frames)
            entry["limit"] = {"overrides": list(knob.limit), "displacement_mm": lim["displacement_mm"],
                              "mean_thrust_mN": lim["mean_thrust_mN"], "wall_s": lim["wall_s"],
                              "failures": lim["failures"]}
            if i is not None:
                d_lim = np.asarray(lim["displacement_mm"])
                entry["default_error_vs_limit"] = ((d[i] - d_lim) / np.abs(d_lim)).tolist()
        results[name] = entry
    return results
