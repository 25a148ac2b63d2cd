"""Half-width profiles w(X) of the 2D fish and their validation (docs/physics.md section 2).

A profile is a vectorised callable ``w(X) -> half-width``: X [...] in metres along the body
(X = 0 at the tail, X = L at the head), w [...] in metres, the body occupying |Y| <= w(X).
Built-ins are made by constructors that return such a callable (`kern_profile`,
`polynomial_profile`); `make_profile` also accepts a user's own callable.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from fishsim.errors import ConfigError, MeshError

Profile = Callable[[np.ndarray], np.ndarray]

#: Default polynomial coefficients c_k of w(X)/L = sum_k c_k (X/L)^k (ascending powers): a
#: least-squares fit of the Kern profile with w(0) = 0.005 L (blunt tail tip), w(L) = 0 and
#: nose slope -dw/dX = 0.6 (a 62 degree nose), max 0.043 L at X = 0.81 L.
DEFAULT_POLY_COEFFS = (0.005, 0.011, 0.748, -2.869, 4.025, -1.92)

#: Number of samples `check_profile` uses to look for non-positive widths.
N_CHECK = 4001


def kern_profile(length: float, w_h: float | None = None, s_b: float | None = None,
                 s_t: float | None = None, w_t: float | None = None) -> Profile:
    """Kern & Koumoutsakos 2006 / Gazzola et al. 2011 profile, with s = L - X from the head:

        w(s) = sqrt(2 w_h s - s^2)                          0   <= s < s_b  (round head)
        w(s) = w_h - (w_h - w_t) ((s - s_b)/(s_t - s_b))^2   s_b <= s < s_t  (body)
        w(s) = w_t (L - s)/(L - s_t)                        s_t <= s <= L   (tail taper)

    Defaults w_h = s_b = 0.04 L, s_t = 0.95 L, w_t = 0.01 L (metres). w is 0 outside [0, L].
    Returns w(X) [...] -> [...] in metres.
    """
    w_h = 0.04 * length if w_h is None else w_h
    s_b = 0.04 * length if s_b is None else s_b
    s_t = 0.95 * length if s_t is None else s_t
    w_t = 0.01 * length if w_t is None else w_t
    if not 0.0 < s_b < s_t < length:
        raise ConfigError(f"kern profile needs 0 < s_b < s_t < L, got s_b={s_b}, s_t={s_t}, L={length}")

    def w(X: np.ndarray) -> np.ndarray:
        s = length - np.asarray(X, dtype=np.float64)
        head = np.sqrt(np.clip(2.0 * w_h * s - s * s, 0.0, None))
        body = w_h - (w_h - w_t) * ((s - s_b) / (s_t - s_b)) ** 2
        tail = w_t * (length - s) / (length - s_t)
        out = np.where(s < s_b, head, np.where(s < s_t, body, tail))
        return np.where((s >= 0.0) & (s <= length), out, 0.0)

    return w


def polynomial_profile(length: float, coeffs=DEFAULT_POLY_COEFFS) -> Profile:
    """Polynomial profile w(X) = L sum_k c_k (X/L)^k, coefficients c_k dimensionless, ascending.

    Returns w(X) [...] -> [...] in metres (0 outside [0, L]).
    """
    c = np.asarray(coeffs, dtype=np.float64)
    if c.ndim != 1 or c.size == 0 or not np.all(np.isfinite(c)):
        raise ConfigError(f"poly_coeffs must be a non-empty list of finite numbers, got {coeffs!r}")

    def w(X: np.ndarray) -> np.ndarray:
        xi = np.asarray(X, dtype=np.float64) / length
        out = length * np.polynomial.polynomial.polyval(xi, c)
        return np.where((xi >= 0.0) & (xi <= 1.0), out, 0.0)

    return w


def make_profile(profile: str | Profile, length: float, poly_coeffs=None) -> Profile:
    """Resolve a profile choice: "kern", "polynomial" (with `poly_coeffs`, default
    `DEFAULT_POLY_COEFFS`) or a user callable w(X) -> half-width in metres."""
    if callable(profile):
        return _as_vectorised(profile)
    if profile == "kern":
        return kern_profile(length)
    if profile in ("polynomial", "poly"):
        return polynomial_profile(length, DEFAULT_POLY_COEFFS if poly_coeffs is None else poly_coeffs)
    raise ConfigError(f"unknown fish profile {profile!r}; use 'kern', 'polynomial' or a callable w(X)")


def _as_vectorised(fn: Callable) -> Profile:
    """Wrap a user callable so it always returns a float64 array shaped like its input."""

    def w(X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float64)
        try:
            out = np.asarray(fn(X), dtype=np.float64)
        except Exception as err:  # the user's function failed on an array: say so plainly
            raise MeshError(f"the profile callable failed on an array of X values ({err}); "
                            "it must map an array X [m] to half-widths w(X) [m]") from err
        if out.shape != X.shape:
            out = np.broadcast_to(out, X.shape).astype(np.float64)
        return out

    return w


def check_profile(w: Profile, length: float, n: int = N_CHECK) -> None:
    """Raise `MeshError` unless w(X) is finite on [0, L] and positive strictly inside (0, L)
    (checked on n equispaced samples)."""
    if not (np.isfinite(length) and length > 0.0):
        raise ConfigError(f"fish length must be a positive number of metres, got {length}")
    X = np.linspace(0.0, length, n)
    wX = w(X)
    if not np.all(np.isfinite(wX)):
        bad = X[~np.isfinite(wX)][0]
        raise MeshError(f"fish profile is not finite at X = {bad:.4g} m; fix the profile function")
    inside = wX[1:-1]
    if np.any(inside <= 0.0):
        bad = X[1:-1][inside <= 0.0][0]
        raise MeshError(f"fish profile has non-positive half-width {w(np.array([bad]))[0]:.3g} m at "
                        f"X = {bad:.4g} m (of L = {length:g} m); the width must be > 0 strictly "
                        "inside (0, L): fix the profile or its poly_coeffs")
    if wX[0] < 0.0 or wX[-1] < 0.0:
        raise MeshError("fish profile has a negative half-width at the tail (X = 0) or head (X = L); "
                        "fix the profile or its poly_coeffs")


def polygon_signed_area(xy: np.ndarray) -> float:
    """Shoelace area of a closed polygon xy [M, 2] (last vertex not repeated), m^2;
    > 0 for counter-clockwise order."""
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def check_outline(xy: np.ndarray) -> None:
    """Raise `MeshError` unless the closed polygon xy [M, 2] is simple (no two non-adjacent
    edges touch or cross) and counter-clockwise. O(M^2) memory/time: fine for M ~ 10^3."""
    if len(xy) < 3:
        raise MeshError(f"fish outline has only {len(xy)} points; a closed outline needs >= 3")
    hit = _crossing_edges(xy)
    if hit is not None:
        i, j = hit
        raise MeshError(f"fish outline self-intersects (edges {i} and {j} near X = {xy[i, 0]:.4g} m); "
                        "the profile half-width must stay > 0 inside the body")
    if polygon_signed_area(xy) <= 0.0:
        raise MeshError("fish outline is not counter-clockwise (signed area <= 0)")


def _orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Twice the signed area of triangles (a, b, c), arrays [..., 2] -> [...]."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def _crossing_edges(xy: np.ndarray):
    """First pair (i, j) of non-adjacent polygon edges i: xy[i] -> xy[i+1] that touch or cross,
    or None."""
    m = len(xy)
    p, q = xy, np.roll(xy, -1, axis=0)
    i, j = np.triu_indices(m, k=2)
    keep = ~((i == 0) & (j == m - 1))  # first and last edges share vertex 0
    i, j = i[keep], j[keep]
    d1, d2 = _orient(p[j], q[j], p[i]), _orient(p[j], q[j], q[i])
    d3, d4 = _orient(p[i], q[i], p[j]), _orient(p[i], q[i], q[j])
    cross = (d1 * d2 <= 0.0) & (d3 * d4 <= 0.0)
    collinear = (d1 == 0.0) & (d2 == 0.0)
    lo_i, hi_i = np.minimum(p[i], q[i]), np.maximum(p[i], q[i])
    lo_j, hi_j = np.minimum(p[j], q[j]), np.maximum(p[j], q[j])
    overlap = np.all((lo_i <= hi_j) & (lo_j <= hi_i), axis=1)
    hit = np.flatnonzero(cross & (~collinear | overlap))
    return None if hit.size == 0 else (int(i[hit[0]]), int(j[hit[0]]))
