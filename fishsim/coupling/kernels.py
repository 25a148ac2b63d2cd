"""Compiled (numba) coupling on the CPU: the band's nearest surface elements and inside flags
(``band_selection``, no gradient), the mask and boundary velocity of every band cell
(``BandBoundary``) and the IBM pressure force with ibm.py's default sampling and any of its
fits, the wall's included (``OutsidePressureForce``), both with hand-written adjoints. They
compute band.py's, mask.py's and ibm.py's formulas, which stay as the reference
(tests/coupling/test_kernels.py) and run on CUDA and for the other options. Solid -> fluid:

    e_l  = |x - c_l|^2,  c_l = a_l + t_l (a_l' - a_l),  t_l = clamp((x - a_l).(a_l' - a_l) / |a_l' - a_l|^2, 0, 1)
    w_l  = softmin weights of e / T over the cell's K' nearest elements (mask.softmin_weights)
    d    = 1 / sum_l (w_l(xi) / max(e_l, 1e-8 xi))   (harmonic)   |   sum_l w_l(xi) e_l   (arithmetic)
    b    = sigmoid(delta d / sigma),   u = sum_l w_l(tau) ((1 - t_l) qdot^l + t_l qdot^l')

with a_l = q^l, a_l' = q^(l+1) (segments; nodes: c_l = q^l, t_l = 0). One pass over a cell's K'
elements replaces ~100 torch operations on [B, P, K'] tensors; the adjoint recomputes e, t and
the weights and scatters dL/dq and dL/dqdot into the surface nodes.

The arithmetic is float64 whatever the fluid's dtype. A batch's fish run in parallel (prange); a
single fish's forward is cut into one block of cells (rows) or nodes per torch thread
(``_each_fish``; the result bit for bit one thread's), its adjoints run in the calling thread.
The band's selection ranks elements by the same squared distances in float64 (band.py ranks
float32 ones), so near-ties at the K'-th element may pick another one; its weight is ~0 there
by the tapered softmin's construction.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
import torch
from numba import prange
from torch import Tensor

from fishsim.compiled import jit, serial_here
from fishsim.fields import MASK_FLOOR


def _f64(t: Tensor) -> np.ndarray:
    """A tensor as a C-contiguous float64 numpy array (a copy unless it already is one)."""
    return np.ascontiguousarray(t.detach().to(torch.float64).numpy())


def _surface_f64(t: Tensor, surface: np.ndarray | None) -> np.ndarray:
    """The surface nodes ``surface`` [S] of t [B, N, 2] (all of t if None) as a C-contiguous float64
    array [B, S, 2]."""
    return _f64(t) if surface is None else np.ascontiguousarray(t.detach().numpy()[:, surface], np.float64)


def _on_nodes(g: np.ndarray, surface: np.ndarray | None, shape: tuple) -> np.ndarray:
    """A gradient g [B, S, 2] on the surface nodes as one on all nodes [B, N, 2] = ``shape``
    (zeros elsewhere; g itself if ``surface`` is None)."""
    if surface is None:
        return g
    out = np.zeros(shape)
    out[:, surface] = g
    return out


def _flat_grid(t: Tensor, B: int, cells: int) -> np.ndarray:
    """A [B, 1, H, W] field as a C-contiguous numpy array [B, H W] of its own dtype (a view when
    it is contiguous)."""
    return np.ascontiguousarray(t.detach().numpy()).reshape(B, cells)


def _each_fish(one, parallel, *args, split=None) -> None:
    """``parallel(*args)`` over a batch's fish (the arrays' leading dimension); for a single fish
    ``split(*its slices, pieces)``, its work cut into one piece per torch thread run in parallel
    (the same result as ``one``; a parallel region costs ~3 us here), or ``one`` on its slices in
    the calling thread (one thread, no ``split``, or a thread of compiled.in_sample_chunks or of
    the rollout's background recomputation, whose work runs serially beside other work)."""
    if next(a for a in args if isinstance(a, np.ndarray)).shape[0] > 1:
        parallel(*args)
        return
    fish = tuple(a[0] if isinstance(a, np.ndarray) else a for a in args)
    pieces = 1 if split is None or serial_here() else torch.get_num_threads()
    if pieces > 1:
        split(*fish, pieces)
    else:
        one(*fish)


# ---------------------------------------------------------------------------------------------
# The band's cells, nearest elements and inside flags


@jit
def _window(lo, hi, n, margin, first):
    """band._window on the fish's extents lo, hi [B] (cell units): writes the origins into
    first [B]; returns the common size."""
    size = 0
    for f in range(lo.shape[0]):
        first[f] = math.floor(lo[f]) - margin
        size = max(size, math.floor(hi[f]) + margin - first[f] + 1)
    size = min(size, n)
    for f in range(lo.shape[0]):
        first[f] = min(max(first[f], 0), n - size)
    return size


@jit
def _band_cells(q, dx, H, W, margin):
    """band._band_cells and the band's origin for the polylines q [B, S, 2] (m): (flat [B, P],
    centres [B, P, 2] relative to the origin, origin [B, 2] the bounding boxes' centres, h, w),
    with the same float operations."""
    B, S = q.shape[0], q.shape[1]
    lo, hi = np.empty((2, B)), np.empty((2, B))
    origin = np.empty((B, 2))
    for f in range(B):
        for c in range(2):
            a, z = q[f, 0, c], q[f, 0, c]
            for s in range(1, S):
                a, z = min(a, q[f, s, c]), max(z, q[f, s, c])
            lo[c, f], hi[c, f], origin[f, c] = a / dx, z / dx, 0.5 * (a + z)
    i0, j0 = np.empty(B, np.int64), np.empty(B, np.int64)
    h, w = _window(lo[1], hi[1], H, margin, i0), _window(lo[0], hi[0], W, margin, j0)
    flat, centres = np.empty((B, h * w), np.int64), np.empty((B, h * w, 2))
    for f in range(B):
        for a in range(h):
            for c in range(w):
                i, j, p = i0[f] + a, j0[f] + c, a * w + c
                flat[f, p] = i * W + j
                centres[f, p, 0] = (j + 0.5) * dx - origin[f, 0]
                centres[f, p, 1] = (i + 0.5) * dx - origin[f, 1]
    return flat, centres, origin, h, w


@jit
def _select(d, index, n, k):
    """Partially order index[:n] (and d[:n] alike) so that its first k entries hold the k
    smallest d (quickselect, Hoare partition)."""
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = d[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while d[i] < pivot:
                i += 1
            while d[j] > pivot:
                j -= 1
            if i <= j:
                d[i], d[j] = d[j], d[i]
                index[i], index[j] = index[j], index[i]
                i += 1
                j -= 1
        if k - 1 <= j:
            hi = j
        elif k - 1 >= i:
            lo = i
        else:
            return


_CHUNK = 8   # consecutive surface elements sharing one bounding box in the nearest-element search


@jit
def _beyond(box, x0, y, far):
    """Whether the point (x0, y) is farther than sqrt(far) from every chunk's bounding box."""
    for c in range(box.shape[0]):
        gx = max(box[c, 0] - x0, 0.0, x0 - box[c, 1])
        gy = max(box[c, 2] - y, 0.0, y - box[c, 3])
        if gx * gx + gy * gy <= far:
            return False
    return True


@jit
def _fish_nearest(q, centres, width, segment, far, nearest, inside, unranked):
    """For each cell p of one fish's window (rows of ``width`` cells, row-major): its
    nearest.shape[1] nearest elements and whether its centre is inside the polyline (even-odd
    rule: crossings of the horizontal ray to +x, found once per row).  A cell outside the body
    whose squared distance to every element's bounding box exceeds ``far`` (m^2) gets the first
    elements instead of ranking them, flagged in ``unranked`` (BandBoundary gives it b = v_d = 0
    without looking at its elements: ``_far`` would find them all beyond ``far``)."""
    _rows_nearest(q, centres, width, segment, far, nearest, inside, unranked, 0, centres.shape[0] // width)


@jit
def _row_crossings(ax, ay, abx, aby, y, crossing):
    """The x of the polyline's crossings with the line at height y, in crossing[:n]; returns n."""
    n = 0
    for l in range(ax.shape[0]):
        if (ay[l] > y) != (ay[l] + aby[l] > y):
            crossing[n] = ax[l] + (y - ay[l]) * abx[l] / aby[l]
            n += 1
    return n


@jit
def _rows_nearest(q, centres, width, segment, far, nearest, inside, unranked, first_row, last_row):
    """``_fish_nearest`` on the window's rows first_row..last_row - 1 only, with the same
    candidates, hence the same elements in the same order, as a pass over all rows.

    The distance to the polyline is 1-Lipschitz, so the k-th nearest squared distance of a cell
    is at most (sqrt(D) + |x - x'|)^2 with D that of a ranked cell x': the row's previous ranked
    cell, or for a row's first ranked cell the previous row's first (for first_row, found by
    ranking that cell among all elements: its D is the same exact k-th distance). Only elements
    within it are ranked (~k + a few of S), and chunks of _CHUNK elements whose bounding box lies
    beyond it are skipped."""
    S, k = q.shape[0], nearest.shape[1]
    ax, ay, abx, aby, inv = np.empty(S), np.empty(S), np.empty(S), np.empty(S), np.empty(S)
    for l in range(S):
        m = l + 1 if l + 1 < S else 0
        ax[l], ay[l] = q[l, 0], q[l, 1]
        abx[l], aby[l] = q[m, 0] - q[l, 0], q[m, 1] - q[l, 1]
        inv[l] = 1.0 / (abx[l] * abx[l] + aby[l] * aby[l]) if segment else 0.0
    chunks = -(-S // _CHUNK)
    box = np.empty((chunks, 4))                                 # x_min, x_max, y_min, y_max
    for c in range(chunks):
        box[c, 0], box[c, 1], box[c, 2], box[c, 3] = np.inf, -np.inf, np.inf, -np.inf
        for l in range(c * _CHUNK, min(S, (c + 1) * _CHUNK)):
            for x, y in ((ax[l], ay[l]), (ax[l] + abx[l], ay[l] + aby[l])):
                box[c, 0], box[c, 1] = min(box[c, 0], x), max(box[c, 1], x)
                box[c, 2], box[c, 3] = min(box[c, 2], y), max(box[c, 3], y)
    d, index, crossing = np.empty(S), np.empty(S, np.int64), np.empty(S)
    first_kth, first_x, first_y = np.inf, 0.0, 0.0              # the previous row's first ranked cell
    for row in range(first_row - 1, -1, -1):                    # the rows before this block's
        y = centres[row * width, 1]
        n_cross = _row_crossings(ax, ay, abx, aby, y, crossing)
        col = 0
        while col < width and _cell_flags(crossing, n_cross, box, centres[row * width + col, 0], y, far)[1]:
            col += 1
        if col < width:
            x0 = centres[row * width + col, 0]
            first_kth = _kth(ax, ay, abx, aby, inv, x0, y, math.inf, box, k, d, index)
            first_x, first_y = x0, y
            break
    for row in range(first_row, last_row):
        y = centres[row * width, 1]
        n_cross = _row_crossings(ax, ay, abx, aby, y, crossing)
        kth, last_x, ranked = first_kth, first_x, False            # this row's last ranked cell
        for col in range(width):
            p = row * width + col
            x0 = centres[p, 0]
            inside[p], unranked[p] = _cell_flags(crossing, n_cross, box, x0, y, far)
            if unranked[p]:
                for j in range(k):
                    nearest[p, j] = j
                continue
            gap = abs(x0 - last_x) if ranked else math.hypot(x0 - first_x, y - first_y)
            kth = _kth(ax, ay, abx, aby, inv, x0, y, (math.sqrt(kth) + gap) ** 2, box, k, d, index)
            for j in range(k):
                nearest[p, j] = index[j]
            if not ranked:
                first_kth, first_x, first_y = kth, x0, y
            last_x, ranked = x0, True


@jit
def _cell_flags(crossing, n_cross, box, x0, y, far):
    """(inside, unranked) of the cell centred at (x0, y): inside the polyline by the even-odd rule
    on its row's crossings crossing[:n_cross] (those right of x0), unranked if outside and
    farther than sqrt(far) from every chunk of elements (``_beyond``)."""
    right = 0
    for j in range(n_cross):
        right += crossing[j] > x0
    inside = right % 2 == 1
    return inside, not inside and _beyond(box, x0, y, far)


@jit
def _kth(ax, ay, abx, aby, inv, x0, y, bound, box, k, d, index):
    """The k nearest elements of the point (x0, y) in index[:k] (their squared distances in
    d[:k]), ranked among those within the squared distance ``bound`` (every element if fewer
    than k lie within it); returns the k-th nearest squared distance."""
    S, chunks = ax.shape[0], box.shape[0]
    n = 0
    for c in range(chunks):
        gx = max(box[c, 0] - x0, 0.0, x0 - box[c, 1])
        gy = max(box[c, 2] - y, 0.0, y - box[c, 3])
        if gx * gx + gy * gy > bound:
            continue
        for l in range(c * _CHUNK, min(S, (c + 1) * _CHUNK)):
            rx, ry = x0 - ax[l], y - ay[l]
            t = min(max((rx * abx[l] + ry * aby[l]) * inv[l], 0.0), 1.0)
            e = (rx - t * abx[l]) ** 2 + (ry - t * aby[l]) ** 2
            if e <= bound:
                d[n], index[n] = e, l
                n += 1
    if n < k:                                   # round-off in the bound: rank them all
        n = S
        for l in range(S):
            rx, ry = x0 - ax[l], y - ay[l]
            t = min(max((rx * abx[l] + ry * aby[l]) * inv[l], 0.0), 1.0)
            d[l], index[l] = (rx - t * abx[l]) ** 2 + (ry - t * aby[l]) ** 2, l
    if k < n:
        _select(d, index, n, k)
    kth = 0.0
    for j in range(k):
        kth = max(kth, d[j])
    return kth


@jit(parallel=True)
def _nearest_parallel(q, centres, width, segment, far, nearest, inside, unranked):
    for b in prange(q.shape[0]):
        _fish_nearest(q[b], centres[b], width, segment, far, nearest[b], inside[b], unranked[b])


@jit(parallel=True)
def _nearest_split(q, centres, width, segment, far, nearest, inside, unranked, pieces):
    """_fish_nearest of one fish, its rows in ``pieces`` blocks in parallel (the same result)."""
    rows = centres.shape[0] // width
    for c in prange(pieces):
        _rows_nearest(q, centres, width, segment, far, nearest, inside, unranked, c * rows // pieces,
                      (c + 1) * rows // pieces)


def _nearest(q: np.ndarray, x: np.ndarray, k: int, segment: bool, width: int, far: float) -> tuple:
    """The k nearest elements [B, P, k] (int64, in no particular order), inside flags [B, P] and
    unranked flags [B, P] of the band cells x [B, P, 2] (a row-major window ``width`` cells wide)
    for the polylines q [B, S, 2] (both float64, relative to the band's origin, m). Cells outside
    the body farther than sqrt(far) [m] from it get elements 0..k-1, unranked (``_fish_nearest``)."""
    B, P = x.shape[:2]
    nearest, inside, unranked = np.empty((B, P, k), np.int64), np.empty((B, P), np.bool_), np.empty((B, P), np.bool_)
    _each_fish(_fish_nearest, _nearest_parallel, q, x, width, segment, float(far), nearest, inside, unranked,
               split=_nearest_split)
    return nearest, inside, unranked


def _selection(q: np.ndarray, dx: float, H: int, W: int, margin: int, k: int, segment: bool, far: float) -> tuple:
    """The band of the polylines q [B, S, 2] (m, numpy of any float dtype): (flat indices [B, P],
    centres [B, P, 2] relative to the origin and origin [B, 2] (the bounding boxes' centres) in
    q's dtype, q relative to the origin in float64, then ``_nearest``'s nearest, inside and
    unranked, and the window's (h, w)); ``band_selection`` and ``FishOnGrid`` select so."""
    flat, centres, origin, h, w = _band_cells(np.ascontiguousarray(q, np.float64), float(dx), H, W, margin)
    centres, origin = centres.astype(q.dtype, copy=False), origin.astype(q.dtype, copy=False)
    rel = np.ascontiguousarray(q - origin[:, None, :], np.float64)
    nearest, inside, unranked = _nearest(rel, np.ascontiguousarray(centres, np.float64), k, segment, w, far)
    return flat, centres, origin, rel, nearest, inside, unranked, (h, w)


def band_selection(qs: Tensor, dx: float, H: int, W: int, margin: int, k: int, segment: bool,
                   far: float = math.inf) -> tuple:
    """band.py's window of cells (flat indices [B, P], centres [B, P, 2] relative to the origin,
    origin [B, 1, 2] the bounding boxes' centres, in qs's dtype) and each cell's nearest elements,
    inside and unranked flags (``_selection``) for the polylines qs [B, S, 2] (m; CPU), as tensors
    (band.surface_band's CPU path): (flat, centres, origin, nearest, inside, unranked, (h, w));
    ~10 us against ~0.2 ms of small torch operations for the window."""
    flat, centres, origin, _, nearest, inside, unranked, window = _selection(qs.detach().numpy(), dx, H, W, margin,
                                                                            k, segment, far)
    return (torch.from_numpy(flat), torch.from_numpy(centres), torch.from_numpy(origin).unsqueeze(1),
            torch.from_numpy(nearest), torch.from_numpy(inside), torch.from_numpy(unranked), window)


# ---------------------------------------------------------------------------------------------
# The mask and boundary velocity of the band cells, and their adjoint


@jit
def _elements(q, x0, x1, nearest, segment, e, t, raw):
    """e, t (clamped) and the unclamped t of the cell's elements ``nearest`` [K]."""
    S = q.shape[0]
    for k in range(nearest.shape[0]):
        l = nearest[k]
        ax, ay = q[l, 0], q[l, 1]
        if segment:
            m = l + 1 if l + 1 < S else 0
            abx, aby = q[m, 0] - ax, q[m, 1] - ay
            r = ((x0 - ax) * abx + (x1 - ay) * aby) / (abx * abx + aby * aby)
            c = min(max(r, 0.0), 1.0)
            raw[k], t[k] = r, c
            ax, ay = ax + c * abx, ay + c * aby
        e[k] = (x0 - ax) ** 2 + (x1 - ay) ** 2


# exp(-40) = 4e-18: a weight below this fraction of the nearest element's (exp(0) = 1) is set to
# 0 without evaluating exp (most of a cell's K' elements are that far); below float64 round-off.
NEGLIGIBLE = 40.0


@jit
def _weights(e, temperature, truncated, w, g):
    """mask.softmin_weights of one cell into w [K]: w_k = (g_k - G) / Z with g_k = exp(-(e_k -
    min e) / T) (kept in g) and G = g of the farthest (truncated; else 0). Returns (Z, G)."""
    lo, hi = e.min(), e.max()
    floor = math.exp(-(hi - lo) / temperature) if truncated and hi - lo < NEGLIGIBLE * temperature else 0.0
    total = 0.0
    for k in range(e.shape[0]):
        s = (e[k] - lo) / temperature
        g[k] = math.exp(-s) if s < NEGLIGIBLE else 0.0
        w[k] = max(g[k] - floor, 0.0)
        total += w[k]
    total = max(total, np.finfo(np.float64).tiny)
    for k in range(e.shape[0]):
        w[k] /= total
    return total, floor


@jit
def _weights_adjoint(e, temperature, w, g, total, floor, gw, ge):
    """ge += (dw/de)^T gw for _weights' w, g, Z, G of e:
    dL/dg_k = (gw_k - sum_j gw_j w_j) / Z, dL/dG = -sum_k dL/dg_k, dg_k/de_k = -g_k / T
    (G is g of the farthest element; min e cancels)."""
    mean = 0.0
    for k in range(e.shape[0]):
        mean += gw[k] * w[k]
    g_floor = 0.0
    for k in range(e.shape[0]):
        gv = (gw[k] - mean) / total
        ge[k] -= gv * g[k] / temperature
        g_floor -= gv
    if floor != 0.0:
        ge[e.argmax()] -= g_floor * floor / temperature


@jit
def _soft_distance(e, w, xi, harmonic):
    """mask.soft_distance of one cell from its weights w (temperature xi)."""
    if not harmonic:
        return (w * e).sum()
    floor, total = 1e-8 * xi, 0.0
    for k in range(e.shape[0]):
        if w[k] != 0.0:                                     # most of a cell's elements (_weights)
            total += w[k] / max(e[k], floor)
    return 1.0 / total


@jit
def _velocity(qdot, nearest, t, w):
    """sum_k w_k ((1 - t_k) qdot^l + t_k qdot^l') of one cell's elements (l = nearest[k])."""
    S = qdot.shape[0]
    u0, u1 = 0.0, 0.0
    for k in range(nearest.shape[0]):
        if w[k] == 0.0:
            continue
        l = nearest[k]
        m = l + 1 if l + 1 < S else 0
        s = t[k]
        u0 += w[k] * ((1.0 - s) * qdot[l, 0] + s * qdot[m, 0])
        u1 += w[k] * ((1.0 - s) * qdot[l, 1] + s * qdot[m, 1])
    return u0, u1


# A cell outside the body whose nearest element lies beyond NEGLIGIBLE sigma (1.8 cells at the
# default sigma = 5e-7 m^2) has b = sigmoid(-d / sigma) < sigmoid(-40) = 4e-18, since the soft
# distance d (a weighted mean of e) is at least min e: it is set to b = 0 and v_d = 0 without the
# soft-mins (every consumer reads v_d as b v_d, and 1 - 4e-18 rounds to 1 in float64).


@jit
def _far(e, inside, sigma):
    """Whether a cell (its elements' squared distances e [K]) is negligibly far outside the body."""
    return not inside and e.min() > NEGLIGIBLE * sigma


@jit
def _fish_forward(q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment, truncated, b,
                  u):
    """b [P] and u [P, 2] of one fish's band cells (module docstring); the unranked cells (far
    outside) b = u = 0 at once."""
    _cells_forward(q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment, truncated, b, u,
                   0, centres.shape[0])


@jit(parallel=True)
def _forward_split(q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment, truncated, b,
                   u, pieces):
    """_fish_forward with the cells in ``pieces`` blocks in parallel (each cell's arithmetic as there)."""
    P = centres.shape[0]
    for c in prange(pieces):
        _cells_forward(q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment, truncated, b,
                       u, c * P // pieces, (c + 1) * P // pieces)


@jit
def _cells_forward(q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment, truncated, b,
                   u, first, last):
    """_fish_forward on the cells first..last - 1."""
    K = nearest.shape[1]
    e, t, raw, w, g = np.empty(K), np.zeros(K), np.zeros(K), np.empty(K), np.empty(K)
    for p in range(first, last):
        if unranked[p]:
            b[p], u[p, 0], u[p, 1] = 0.0, 0.0, 0.0
            continue
        _elements(q, centres[p, 0], centres[p, 1], nearest[p], segment, e, t, raw)
        if _far(e, inside[p], sigma):
            b[p], u[p, 0], u[p, 1] = 0.0, 0.0, 0.0
            continue
        _weights(e, xi, truncated, w, g)
        d = _soft_distance(e, w, xi, harmonic)
        b[p] = 1.0 / (1.0 + math.exp(-(d if inside[p] else -d) / sigma))
        if tau != xi:
            _weights(e, tau, truncated, w, g)
        u[p, 0], u[p, 1] = _velocity(qdot, nearest[p], t, w)


@jit
def _fish_backward(q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment, truncated, b, gb,
                   gu, gq, gqdot):
    """gq, gqdot [S, 2] += the adjoint of _fish_forward for the cotangents gb [P], gu [P, 2]."""
    S, K = q.shape[0], nearest.shape[1]
    e, t, raw, w, g = np.empty(K), np.zeros(K), np.zeros(K), np.empty(K), np.empty(K)
    gw, ge, gt = np.empty(K), np.empty(K), np.empty(K)
    floor = 1e-8 * xi
    for p in range(centres.shape[0]):
        if unranked[p]:
            continue
        x0, x1 = centres[p, 0], centres[p, 1]
        _elements(q, x0, x1, nearest[p], segment, e, t, raw)
        if _far(e, inside[p], sigma):
            continue
        ge[:] = 0.0
        gt[:] = 0.0
        gw[:] = 0.0
        total, far = _weights(e, xi, truncated, w, g)
        sign = 1.0 if inside[p] else -1.0                   # mask: b = sigmoid(delta d / sigma)
        gd = gb[p] * b[p] * (1.0 - b[p]) * sign / sigma
        if gd != 0.0:
            if harmonic:
                d = _soft_distance(e, w, xi, harmonic)
                gH = -gd * d * d
                for k in range(K):
                    clamped = max(e[k], floor)
                    gw[k] = gH / clamped
                    if e[k] >= floor:
                        ge[k] -= gH * w[k] / (clamped * clamped)
            else:
                for k in range(K):
                    gw[k] = gd * e[k]
                    ge[k] += gd * w[k]
            if tau != xi:
                _weights_adjoint(e, xi, w, g, total, far, gw, ge)
                gw[:] = 0.0
        g0, g1 = gu[p, 0], gu[p, 1]                         # velocity: u = sum_k w_k V_k
        if g0 != 0.0 or g1 != 0.0:
            if tau != xi:
                total, far = _weights(e, tau, truncated, w, g)
            for k in range(K):
                l = nearest[p, k]
                m = l + 1 if l + 1 < S else 0
                s = t[k]
                gw[k] += g0 * ((1.0 - s) * qdot[l, 0] + s * qdot[m, 0]) + g1 * ((1.0 - s) * qdot[l, 1] + s * qdot[m, 1])
                gt[k] = w[k] * (g0 * (qdot[m, 0] - qdot[l, 0]) + g1 * (qdot[m, 1] - qdot[l, 1]))
                gqdot[l, 0] += w[k] * (1.0 - s) * g0
                gqdot[l, 1] += w[k] * (1.0 - s) * g1
                if segment:
                    gqdot[m, 0] += w[k] * s * g0
                    gqdot[m, 1] += w[k] * s * g1
        _weights_adjoint(e, tau, w, g, total, far, gw, ge)
        for k in range(K):                                  # e, t -> the element's nodes
            l = nearest[p, k]
            ax, ay = q[l, 0], q[l, 1]
            if not segment:
                gq[l, 0] -= 2.0 * ge[k] * (x0 - ax)
                gq[l, 1] -= 2.0 * ge[k] * (x1 - ay)
                continue
            m = l + 1 if l + 1 < S else 0
            abx, aby = q[m, 0] - ax, q[m, 1] - ay
            s = t[k]
            dx_, dy_ = x0 - ax - s * abx, x1 - ay - s * aby        # x - c
            gq[l, 0] -= 2.0 * ge[k] * (1.0 - s) * dx_
            gq[l, 1] -= 2.0 * ge[k] * (1.0 - s) * dy_
            gq[m, 0] -= 2.0 * ge[k] * s * dx_
            gq[m, 1] -= 2.0 * ge[k] * s * dy_
            if gt[k] != 0.0 and 0.0 <= raw[k] <= 1.0:             # dt/da, dt/da' inside the segment
                length2 = abx * abx + aby * aby
                rx, ry = x0 - ax, x1 - ay
                gq[l, 0] += gt[k] * (-abx - rx + 2.0 * s * abx) / length2
                gq[l, 1] += gt[k] * (-aby - ry + 2.0 * s * aby) / length2
                gq[m, 0] += gt[k] * (rx - 2.0 * s * abx) / length2
                gq[m, 1] += gt[k] * (ry - 2.0 * s * aby) / length2


@jit(parallel=True)
def _forward_parallel(q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment, truncated, b,
                      u):
    for n in prange(q.shape[0]):
        _fish_forward(q[n], qdot[n], centres[n], nearest[n], inside[n], unranked[n], xi, sigma, tau, harmonic,
                      segment, truncated, b[n], u[n])


@jit(parallel=True)
def _backward_parallel(q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment, truncated, b,
                       gb, gu, gq, gqdot):
    for n in prange(q.shape[0]):
        _fish_backward(q[n], qdot[n], centres[n], nearest[n], inside[n], unranked[n], xi, sigma, tau, harmonic, segment,
                       truncated, b[n], gb[n], gu[n], gq[n], gqdot[n])


def _band_boundary(args: tuple) -> tuple[np.ndarray, np.ndarray]:
    """(b [B, P], u [B, P, 2]) in float64 of the band cells for ``_fish_forward``'s arguments
    ``args`` = (q, qdot, centres, nearest, inside, unranked, xi, sigma, tau, harmonic, segment,
    truncated)."""
    B, P = args[3].shape[:2]
    b, u = np.empty((B, P)), np.empty((B, P, 2))
    _each_fish(_fish_forward, _forward_parallel, *args, b, u, split=_forward_split)
    return b, u


def _band_boundary_adjoint(args: tuple, b: np.ndarray, gb: np.ndarray, gu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(dL/dq, dL/dqdot) [B, S, 2] of ``_band_boundary(args)`` (its b) for the cotangents gb [B, P]
    and gu [B, P, 2] (float64)."""
    gq, gqdot = np.zeros(args[0].shape), np.zeros(args[1].shape)
    _each_fish(_fish_backward, _backward_parallel, *args, b, gb, gu, gq, gqdot)
    return gq, gqdot


class BandBoundary(torch.autograd.Function):
    """(b [B, P], u [B, P, 2]) of the band cells (module docstring) in ``dtype``, from the surface
    positions qs and velocities qdots [B, S, 2] (m, m/s; relative to the band's origin), the cell
    centres [B, P, 2] (same origin), the elements nearest [B, P, K'], inside [B, P] and unranked
    [B, P] (or None: every cell ranked) of band.py's SurfaceBand; xi, sigma, tau in m^2; CPU
    tensors. Differentiable in qs and qdots."""

    @staticmethod
    def forward(ctx, qs: Tensor, qdots: Tensor, centres: Tensor, nearest: Tensor, inside: Tensor,
                unranked: Tensor | None, xi: float, sigma: float, tau: float, harmonic: bool, segment: bool,
                truncated: bool, dtype: torch.dtype):
        flags = np.zeros(inside.shape, np.bool_) if unranked is None else np.ascontiguousarray(unranked.numpy())
        args = (_f64(qs), _f64(qdots), _f64(centres), np.ascontiguousarray(nearest.numpy()),
                np.ascontiguousarray(inside.numpy()), flags, float(xi), float(sigma), float(tau), bool(harmonic),
                bool(segment), bool(truncated))
        b, u = _band_boundary(args)
        ctx.args, ctx.b, ctx.dtypes = args, b, (qs.dtype, qdots.dtype)
        return torch.from_numpy(b).to(dtype), torch.from_numpy(u).to(dtype)

    @staticmethod
    def backward(ctx, gb: Tensor, gu: Tensor):
        args, b = ctx.args, ctx.b
        gb = np.zeros(b.shape) if gb is None else _f64(gb)
        gu = np.zeros((*b.shape, 2)) if gu is None else _f64(gu)
        gq, gqdot = _band_boundary_adjoint(args, b, gb, gu)
        q_dtype, qdot_dtype = ctx.dtypes
        return (torch.from_numpy(gq).to(q_dtype), torch.from_numpy(gqdot).to(qdot_dtype),
                *([None] * 11))


# ---------------------------------------------------------------------------------------------
# The fish united with the tank's walls on the grid (fields.union, formed on the band's cells) in
# one call from the mesh nodes, and its adjoint


@jit
def _union(b, u, flat, wall_mask, wall_velocity, scale, one, floor, mask, velocity):
    """mask [B, H W] and velocity [B, 2, H W]: the walls (wall_mask [1 or B, H W], wall_velocity
    [1 or B, 2, H W] times scale [B]) with each fish's band cells flat [B, P] replaced by
    fields.union((b [B, P], u [B, P, 2]), walls), in the fields' own dtype (``one``, ``floor``: 1
    and fields.MASK_FLOOR in it), the operations in fields.union's order."""
    for f in range(b.shape[0]):
        w = f if wall_mask.shape[0] > 1 else 0
        mask[f] = wall_mask[w]
        for k in range(2):
            for c in range(mask.shape[1]):
                velocity[f, k, c] = wall_velocity[w, k, c] * scale[f]
        for p in range(b.shape[1]):
            c = flat[f, p]
            b_fish, b_wall = b[f, p], wall_mask[w, c]
            mask[f, c] = one - (one - b_fish) * (one - b_wall)
            total = max(b_fish + b_wall, floor)
            for k in range(2):
                velocity[f, k, c] = (b_fish * u[f, p, k] + b_wall * (wall_velocity[w, k, c] * scale[f])) / total


@jit
def _union_adjoint(b, u, flat, wall_mask, wall_velocity, scale, floor, g_mask, g_velocity, need_scale, gb, gu,
                   g_scale):
    """gb [B, P], gu [B, P, 2] and g_scale [B] (if ``need_scale``) of _union for the cotangents
    g_mask [B, H W] and g_velocity [B, 2, H W], in float64 (b, u, scale and the cotangents float64;
    the walls may be float32: each of their entries meets a float64 operand)."""
    for f in range(b.shape[0]):
        w = f if wall_mask.shape[0] > 1 else 0
        total_scale = 0.0
        if need_scale:                                      # velocity = scale v_wall off the band
            for k in range(2):
                for c in range(g_velocity.shape[2]):
                    total_scale += g_velocity[f, k, c] * wall_velocity[w, k, c]
        for p in range(b.shape[1]):
            c = flat[f, p]
            b_fish, b_wall = b[f, p], wall_mask[w, c]
            raw = b_fish + b_wall
            total = max(raw, floor)
            g_b = g_mask[f, c] * (1.0 - b_wall)
            for k in range(2):
                v_wall = wall_velocity[w, k, c] * scale[f]
                v = (b_fish * u[f, p, k] + b_wall * v_wall) / total
                g_v = g_velocity[f, k, c]
                gu[f, p, k] = g_v * b_fish / total
                g_b += g_v * ((u[f, p, k] - v) / total if raw > floor else u[f, p, k] / total)
                if need_scale:
                    total_scale += g_v * (b_wall / total - 1.0) * wall_velocity[w, k, c]
            gb[f, p] = g_b
        g_scale[f] = total_scale


BandSettings = namedtuple("BandSettings", "dx H W margin k segment far xi sigma tau harmonic truncated")
BandSettings.__doc__ = """What ``FishOnGrid`` needs besides the tensors: the grid (cell size dx in m, H x W cells),
the band's margin (cells) and k nearest elements (band.surface_band), segments or nodes, the
squared distance beyond which an outside cell is negligible (m^2), the mask's xi, sigma and the
velocity's tau (m^2), the harmonic or arithmetic soft distance, the truncated soft-mins."""


class FishOnGrid(torch.autograd.Function):
    """(mask [B, 1, H, W], velocity [B, 2, H, W]) = fields.union(fish, walls) from the mesh nodes
    q, qdot [B, N, 2] (m, m/s; the nodes ``surface`` [S] (numpy) make the fish's polyline) in one
    call: the band's window and nearest elements (``band_selection``), the mask and velocity of its
    cells (``BandBoundary``'s formulas, float64) rounded to the walls' dtype, and their union with
    the walls (wall_mask [1 or B, 1, H, W], wall_velocity [1 or B, 2, H, W]: constants, as
    layer.united_with_nothing gives them) whose velocity is scaled by scale [B] (a swim tunnel's
    -U) on the band's cells only (``_union``, in the walls' dtype, fields.union's order). Off the band
    the fish's b is 0 and the union is the walls. The same values bit for bit as layer.fish_band
    followed by the union of ``layer.torch_band_union``, without their ~30 small torch operations
    (0.3-0.4 ms a frame at B = 1). The adjoint runs in float64 (scale's gradient is returned in
    its own dtype). CPU tensors; differentiable in q, qdot and scale."""

    @staticmethod
    def forward(ctx, q: Tensor, qdot: Tensor, scale: Tensor, wall_mask: Tensor, wall_velocity: Tensor,
                surface: np.ndarray, settings: BandSettings):
        if wall_mask.requires_grad or wall_velocity.requires_grad:
            raise ValueError("FishOnGrid: the walls are constants (their velocity varies through ``scale``)")
        st, cells = settings, settings.H * settings.W
        flat, centres, _, rel, nearest, inside, unranked, _ = _selection(
            _surface_f64(q, surface), st.dx, st.H, st.W, st.margin, st.k, st.segment, st.far)
        args = (rel, _surface_f64(qdot, surface), centres, nearest, inside, unranked, st.xi, st.sigma, st.tau,
                st.harmonic, st.segment, st.truncated)
        b, u = _band_boundary(args)
        walls = (_flat_grid(wall_mask, wall_mask.shape[0], cells),
                 np.ascontiguousarray(wall_velocity.detach().numpy()).reshape(-1, 2, cells))
        fields = walls[0].dtype
        union = (b.astype(fields), u.astype(fields), flat, *walls, scale.detach().numpy().astype(fields))
        B = flat.shape[0]
        mask, velocity = np.empty((B, cells), fields), np.empty((B, 2, cells), fields)
        _union(*union, fields.type(1.0), fields.type(MASK_FLOOR), mask, velocity)
        ctx.args, ctx.b, ctx.union, ctx.surface = args, b, union, surface
        ctx.shapes = (q.shape, q.dtype, qdot.dtype, scale.dtype)
        return torch.from_numpy(mask).view(B, 1, st.H, st.W), torch.from_numpy(velocity).view(B, 2, st.H, st.W)

    @staticmethod
    def backward(ctx, g_mask: Tensor, g_velocity: Tensor):
        b_d, u_d, flat, wall_mask, wall_velocity, scale = ctx.union
        (B, P), cells = b_d.shape, wall_mask.shape[-1]
        g_mask = np.zeros((B, cells)) if g_mask is None else _f64(g_mask).reshape(B, cells)
        g_velocity = np.zeros((B, 2, cells)) if g_velocity is None else _f64(g_velocity).reshape(B, 2, cells)
        gb, gu, g_scale = np.empty((B, P)), np.empty((B, P, 2)), np.zeros(B)
        # the walls as they are (constant grids: a float32 entry meets a float64 operand in every
        # product and sum of the adjoint, so it reads exactly as its float64 copy would)
        _union_adjoint(b_d.astype(np.float64), u_d.astype(np.float64), flat, wall_mask, wall_velocity,
                       scale.astype(np.float64), MASK_FLOOR, g_mask, g_velocity, ctx.needs_input_grad[2], gb, gu,
                       g_scale)
        gq_s, gqdot_s = _band_boundary_adjoint(ctx.args, ctx.b, gb, gu)
        shape, q_dtype, qdot_dtype, scale_dtype = ctx.shapes
        gq, gqdot = _on_nodes(gq_s, ctx.surface, shape), _on_nodes(gqdot_s, ctx.surface, shape)
        return (torch.from_numpy(gq).to(q_dtype), torch.from_numpy(gqdot).to(qdot_dtype),
                torch.from_numpy(g_scale).to(scale_dtype), None, None, None, None)


# ---------------------------------------------------------------------------------------------
# Fluid -> solid: the IBM pressure force f_k = -p_k a_k with ibm.py's default sampling ("outside"
# weights, "chord" elements; "linear" or "mean" fit), and its adjoint


@jit
def _taper(u, inner, outer):
    """ibm.taper(u, inner, outer) and its derivative in u."""
    s = (outer - abs(u)) / (outer - inner)
    if s <= 0.0:
        return 0.0, 0.0
    if s >= 1.0:
        return 1.0, 0.0
    slope = 30.0 * s * s * (1.0 - s) * (1.0 - s)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s), -slope * np.sign(u) / (outer - inner)


@jit
def _chord(q, k):
    """The chord element a_k = J (q^(k+1) - q^(k-1)) / 2 of node k and the ends' indices."""
    S = q.shape[0]
    after, before = (k + 1) % S, (k - 1) % S
    return 0.5 * (q[after, 1] - q[before, 1]), -0.5 * (q[after, 0] - q[before, 0]), after, before


@jit
def _samples(q, k, nx, ny, mask, outside, shape, dx, sigma_prime, radius, cell, ox, oy, weight):
    """The cells among the (2r+1)^2 around node k that node k samples (ibm.sample_weights): their
    flat index (cell), offsets x_ij - q^k (ox, oy) and weights g_ij S(b_ij) H(n.(x_ij - q^k)) > 0,
    in the first m entries of the arrays; returns (the weights' sum, m). The cells a node does not
    sample (beyond the grid, on the body's side, in the mask's band) would add only zeros to the
    fit and its adjoint. The kernel g_ij = exp(-|x_ij - q^k|^2 / (2 sigma')) T(x) T(y) is
    separable: its factors are taken once per column and row."""
    H, W = shape
    cj, ci = math.floor(q[k, 0] / dx), math.floor(q[k, 1] / dx)
    inner, outer = (radius - 1) * dx, (radius + 0.5) * dx
    n = 2 * radius + 1
    along_x, along_y = np.empty(n), np.empty(n)
    for a in range(n):
        x, y = (cj - radius + a + 0.5) * dx - q[k, 0], (ci - radius + a + 0.5) * dx - q[k, 1]
        along_x[a] = math.exp(-x * x * (0.5 / sigma_prime)) * _taper(x, inner, outer)[0]
        along_y[a] = math.exp(-y * y * (0.5 / sigma_prime)) * _taper(y, inner, outer)[0]
    total, m = 0.0, 0
    for i in range(max(ci - radius, 0), min(ci + radius + 1, H)):
        for j in range(max(cj - radius, 0), min(cj + radius + 1, W)):
            x, y = (j + 0.5) * dx - q[k, 0], (i + 0.5) * dx - q[k, 1]
            w = along_x[j - cj + radius] * along_y[i - ci + radius]
            if w == 0.0:
                continue
            w *= _taper(min(nx * x + ny * y - dx, 0.0), 0.0, dx)[0]      # the body's side of the node: 0
            if w == 0.0:
                continue
            w *= _taper(mask[i * W + j], 0.0, outside)[0]
            if w == 0.0:
                continue
            cell[m], ox[m], oy[m], weight[m] = i * W + j, x, y, w
            total += w
            m += 1
    return total, m


#: The IBM fits the compiled force knows (ibm.py's "mean", "linear" and "wall").
MEAN_FIT, LINEAR_FIT, WALL_FIT = 0, 1, 2


@jit
def _fit(p, cell, ox, oy, wn, m, sigma_prime, linear, d):
    """p_k (ibm.fit_at_node) from the first m samples' normalised weights wn; with ``linear``
    also d (the plane fit's coefficients, ibm.linear_fit_correction) and returns (p_k, pbar, rx,
    ry, ux, uy, det, cxx, cyy, cxy)."""
    pbar, rx, ry = 0.0, 0.0, 0.0
    for c in range(m):
        pbar += wn[c] * p[cell[c]]
        rx += wn[c] * ox[c]
        ry += wn[c] * oy[c]
    if not linear:
        return pbar, pbar, rx, ry, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0
    cxx, cyy, cxy = 1e-6 * sigma_prime, 1e-6 * sigma_prime, 0.0
    for c in range(m):
        ex, ey = ox[c] - rx, oy[c] - ry
        cxx += wn[c] * ex * ex
        cyy += wn[c] * ey * ey
        cxy += wn[c] * ex * ey
    det = cxx * cyy - cxy * cxy
    ux, uy = (cyy * rx - cxy * ry) / det, (cxx * ry - cxy * rx) / det
    p_k = pbar
    for c in range(m):
        d[c] = -wn[c] * (ux * (ox[c] - rx) + uy * (oy[c] - ry))
        p_k += d[c] * (p[cell[c]] - pbar)
    return p_k, pbar, rx, ry, ux, uy, det, cxx, cyy, cxy


@jit
def _wall_fit(p, cell, ox, oy, wn, m, nx, ny, slope, sigma_prime, y, s):
    """p_k of the "wall" fit (ibm.fit_at_node): the line y ~ c + g s through the samples y = p - G h
    (h = n.o, s = n x o the offsets along the normal and the tangent, G = ``slope`` the imposed
    dp/dn), weighted by wn, regularised as ibm._wall_fit; fills y and s and returns (p_k, ybar,
    sbar, g, den) (g = num / den the line's slope)."""
    ybar, sbar = 0.0, 0.0
    for c in range(m):
        s[c] = nx * oy[c] - ny * ox[c]
        y[c] = p[cell[c]] - slope * (nx * ox[c] + ny * oy[c])
        ybar += wn[c] * y[c]
        sbar += wn[c] * s[c]
    num, den = 0.0, 1e-6 * sigma_prime
    for c in range(m):
        ds = s[c] - sbar
        num += wn[c] * ds * (y[c] - ybar)
        den += wn[c] * ds * ds
    g = num / den
    return ybar - g * sbar, ybar, sbar, g, den


@jit
def _fish_ibm(q, p, mask, outside, shape, dx, sigma_prime, radius, fit, acc, rho, f):
    """f [S, 2] = -p_k a_k of one fish (p, mask: its flat [H W] fields; fit: MEAN_FIT, LINEAR_FIT
    or WALL_FIT, the last with the nodes' accelerations acc [S, 2] and the fluid's density rho)."""
    _nodes_ibm(q, p, mask, outside, shape, dx, sigma_prime, radius, fit, acc, rho, f, 0, q.shape[0])


@jit(parallel=True)
def _ibm_split(q, p, mask, outside, shape, dx, sigma_prime, radius, fit, acc, rho, f, pieces):
    """_fish_ibm with the nodes in ``pieces`` blocks in parallel (each node's arithmetic as there)."""
    S = q.shape[0]
    for c in prange(pieces):
        _nodes_ibm(q, p, mask, outside, shape, dx, sigma_prime, radius, fit, acc, rho, f, c * S // pieces,
                   (c + 1) * S // pieces)


@jit
def _node_samples(q, k, mask, outside, shape, dx, sigma_prime, radius, cell, ox, oy, wn):
    """Node k's chord a = (a_x, a_y) with its neighbours' indices (``_chord``), unit normal n =
    a / |a| and fluid samples (``_samples`` into cell, ox, oy, wn), the weights normalised by their
    sum; returns (a_x, a_y, after, before, n_x, n_y, |a|, the raw sum, the divisor used, m)."""
    ax, ay, after, before = _chord(q, k)
    norm = math.sqrt(ax * ax + ay * ay)
    nx, ny = ax / norm, ay / norm
    raw, m = _samples(q, k, nx, ny, mask, outside, shape, dx, sigma_prime, radius, cell, ox, oy, wn)
    total = max(raw, np.finfo(np.float64).tiny)
    for c in range(m):
        wn[c] /= total
    return ax, ay, after, before, nx, ny, norm, raw, total, m


@jit
def _nodes_ibm(q, p, mask, outside, shape, dx, sigma_prime, radius, fit, acc, rho, f, first, last):
    """_fish_ibm's f on the nodes first..last - 1."""
    M = (2 * radius + 1) ** 2
    cell, ox, oy, wn, d = np.empty(M, np.int64), np.empty(M), np.empty(M), np.empty(M), np.empty(M)
    tangential = np.empty(M)
    for k in range(first, last):
        ax, ay, _, _, nx, ny, _, _, _, m = _node_samples(q, k, mask, outside, shape, dx, sigma_prime, radius,
                                                         cell, ox, oy, wn)
        if fit == WALL_FIT:
            slope = -rho * (acc[k, 0] * nx + acc[k, 1] * ny)
            p_k = _wall_fit(p, cell, ox, oy, wn, m, nx, ny, slope, sigma_prime, d, tangential)[0]
        else:
            p_k = _fit(p, cell, ox, oy, wn, m, sigma_prime, fit == LINEAR_FIT, d)[0]
        f[k, 0], f[k, 1] = -p_k * ax, -p_k * ay


@jit
def _wall_fit_adjoint(p, cell, ox, oy, wn, m, nx, ny, slope, sigma_prime, y, s, g_pk, gp, g_wn, g_ox, g_oy):
    """The adjoint of ``_wall_fit`` for the cotangent g_pk of its p_k: adds to gp [H W] and to the
    samples' g_wn, g_ox, g_oy; returns (the p_k, the cotangents of n_x, n_y and of the slope)."""
    p_k, ybar, sbar, g, den = _wall_fit(p, cell, ox, oy, wn, m, nx, ny, slope, sigma_prime, y, s)
    g_num, g_sbar, g_ybar = -g_pk * sbar / den, -g_pk * g, g_pk       # p_k = ybar - (num / den) sbar
    g_den = -g_num * g
    for c in range(m):                                   # num, den = sum wn ds dy (+ eps), sum wn ds^2
        ds, dy = s[c] - sbar, y[c] - ybar
        g_sbar -= wn[c] * (g_num * dy + 2.0 * g_den * ds)
        g_ybar -= g_num * wn[c] * ds
    g_nx, g_ny, g_slope = 0.0, 0.0, 0.0
    for c in range(m):
        ds, dy = s[c] - sbar, y[c] - ybar
        g_wn[c] += g_num * ds * dy + g_den * ds * ds + g_sbar * s[c] + g_ybar * y[c]
        g_s = wn[c] * (g_num * dy + 2.0 * g_den * ds) + g_sbar * wn[c]
        g_y = g_num * wn[c] * ds + g_ybar * wn[c]
        gp[cell[c]] += g_y                                   # y = p - slope h, h = n.o, s = n x o
        g_h = -slope * g_y
        g_slope -= g_y * (nx * ox[c] + ny * oy[c])
        g_ox[c] += g_h * nx - g_s * ny
        g_oy[c] += g_h * ny + g_s * nx
        g_nx += g_h * ox[c] + g_s * oy[c]
        g_ny += g_h * oy[c] - g_s * ox[c]
    return p_k, g_nx, g_ny, g_slope


@jit
def _fish_ibm_backward(q, p, mask, outside, shape, dx, sigma_prime, radius, fit, acc, rho, gf, gq, gp, gmask, gacc):
    """gq [S, 2], gp and gmask [H W] (and with WALL_FIT gacc [S, 2]) += the adjoint of _fish_ibm for
    the cotangent gf [S, 2]."""
    M = (2 * radius + 1) ** 2
    cell, ox, oy, wn, d = np.empty(M, np.int64), np.empty(M), np.empty(M), np.empty(M), np.empty(M)
    g_wn, g_ox, g_oy, tangential = np.empty(M), np.empty(M), np.empty(M), np.empty(M)
    inner, outer = (radius - 1) * dx, (radius + 0.5) * dx
    linear = fit == LINEAR_FIT
    for k in range(q.shape[0]):
        ax, ay, after, before, nx, ny, norm, raw, total, m = _node_samples(q, k, mask, outside, shape, dx,
                                                                           sigma_prime, radius, cell, ox, oy, wn)
        g_wn[:m] = 0.0
        g_ox[:m] = 0.0
        g_oy[:m] = 0.0
        g_nx, g_ny = 0.0, 0.0
        g_pk = -(gf[k, 0] * ax + gf[k, 1] * ay)                     # f = -p_k a
        if fit == WALL_FIT:                                         # slope = -rho acc . n
            slope = -rho * (acc[k, 0] * nx + acc[k, 1] * ny)
            p_k, g_nx, g_ny, g_slope = _wall_fit_adjoint(p, cell, ox, oy, wn, m, nx, ny, slope, sigma_prime, d,
                                                         tangential, g_pk, gp, g_wn, g_ox, g_oy)
            gacc[k, 0] -= rho * g_slope * nx
            gacc[k, 1] -= rho * g_slope * ny
            g_nx -= rho * g_slope * acc[k, 0]
            g_ny -= rho * g_slope * acc[k, 1]
        else:
            p_k, pbar, rx, ry, ux, uy, det, cxx, cyy, cxy = _fit(p, cell, ox, oy, wn, m, sigma_prime, linear, d)
        g_ax, g_ay = -p_k * gf[k, 0], -p_k * gf[k, 1]
        g_pbar = g_pk
        if linear:                                                  # p_k = pbar + sum d (p - pbar)
            g_ux, g_uy, g_rx, g_ry = 0.0, 0.0, 0.0, 0.0
            g_cxx, g_cyy, g_cxy = 0.0, 0.0, 0.0
            sum_d, sum_gex, sum_gey = 0.0, 0.0, 0.0
            for c in range(m):
                sum_d += d[c]
                g_d = g_pk * (p[cell[c]] - pbar)
                gp[cell[c]] += g_pk * d[c]
                ex, ey = ox[c] - rx, oy[c] - ry                     # d = -(ux wn ex + uy wn ey)
                g_ux -= g_d * wn[c] * ex
                g_uy -= g_d * wn[c] * ey
                g_ax_c, g_ay_c = -g_d * ux, -g_d * uy               # cotangents of wn ex, wn ey
                g_wn[c] += g_ax_c * ex + g_ay_c * ey
                g_ox[c] += g_ax_c * wn[c]
                g_oy[c] += g_ay_c * wn[c]
                sum_gex += g_ax_c * wn[c]
                sum_gey += g_ay_c * wn[c]
            g_pbar = g_pk * (1.0 - sum_d)
            g_cyy += g_ux * rx / det                                # u = C^-1 r
            g_rx += g_ux * cyy / det
            g_cxy -= g_ux * ry / det
            g_ry -= g_ux * cxy / det
            g_det = -g_ux * ux / det
            g_cxx += g_uy * ry / det
            g_ry += g_uy * cxx / det
            g_cxy -= g_uy * rx / det
            g_rx -= g_uy * cxy / det
            g_det -= g_uy * uy / det
            g_cxx += g_det * cyy                                    # det = cxx cyy - cxy^2
            g_cyy += g_det * cxx
            g_cxy -= 2.0 * g_det * cxy
            for c in range(m):                                      # C = sum wn e e^T (+ eps I)
                ex, ey = ox[c] - rx, oy[c] - ry
                g_wn[c] += g_cxx * ex * ex + g_cyy * ey * ey + g_cxy * ex * ey
                g_ex = wn[c] * (2.0 * g_cxx * ex + g_cxy * ey)
                g_ey = wn[c] * (2.0 * g_cyy * ey + g_cxy * ex)
                g_ox[c] += g_ex
                g_oy[c] += g_ey
                sum_gex += g_ex
                sum_gey += g_ey
            g_rx -= sum_gex                                         # e = o - r
            g_ry -= sum_gey
            for c in range(m):                                      # r = sum wn o
                g_wn[c] += g_rx * ox[c] + g_ry * oy[c]
                g_ox[c] += g_rx * wn[c]
                g_oy[c] += g_ry * wn[c]
        if fit != WALL_FIT:
            for c in range(m):                                      # pbar = sum wn p
                g_wn[c] += g_pbar * p[cell[c]]
                gp[cell[c]] += g_pbar * wn[c]
        mean = 0.0
        for c in range(m):
            mean += g_wn[c] * wn[c]
        g_qx, g_qy = 0.0, 0.0
        for c in range(m):                                          # wn = W / Z, W = g S(b) H(h)
            if wn[c] == 0.0:                                        # (S, H and their slopes vanish there)
                continue
            g_w = (g_wn[c] - mean) / total if raw >= np.finfo(np.float64).tiny else g_wn[c] / total
            x, y = ox[c], oy[c]
            gauss = math.exp(-(x * x + y * y) * (0.5 / sigma_prime))
            tx, dtx = _taper(x, inner, outer)
            ty, dty = _taper(y, inner, outer)
            sb, dsb = _taper(mask[cell[c]], 0.0, outside)
            h = nx * x + ny * y
            side, dside = _taper(min(h - dx, 0.0), 0.0, dx)
            if h - dx > 0.0:
                dside = 0.0
            kernel = gauss * tx * ty
            gmask[cell[c]] += g_w * kernel * side * dsb
            g_h = g_w * kernel * sb * dside
            g_x = g_ox[c] + g_w * sb * side * gauss * (-x / sigma_prime * tx * ty + dtx * ty) + g_h * nx
            g_y = g_oy[c] + g_w * sb * side * gauss * (-y / sigma_prime * tx * ty + tx * dty) + g_h * ny
            g_nx += g_h * x
            g_ny += g_h * y
            g_qx -= g_x                                             # o = x_ij - q^k
            g_qy -= g_y
        gq[k, 0] += g_qx
        gq[k, 1] += g_qy
        along = nx * g_nx + ny * g_ny                               # n = a / |a|
        g_ax += (g_nx - nx * along) / norm
        g_ay += (g_ny - ny * along) / norm
        gq[after, 0] -= 0.5 * g_ay                                  # a = (c_y, -c_x) / 2
        gq[before, 0] += 0.5 * g_ay
        gq[after, 1] += 0.5 * g_ax
        gq[before, 1] -= 0.5 * g_ax


@jit(parallel=True)
def _ibm_parallel(q, p, mask, outside, shape, dx, sigma_prime, radius, fit, acc, rho, f):
    for n in prange(q.shape[0]):
        _fish_ibm(q[n], p[n], mask[n], outside, shape, dx, sigma_prime, radius, fit, acc[n], rho[n], f[n])


@jit(parallel=True)
def _ibm_backward_parallel(q, p, mask, outside, shape, dx, sigma_prime, radius, fit, acc, rho, gf, gq, gp, gmask,
                           gacc):
    for n in prange(q.shape[0]):
        _fish_ibm_backward(q[n], p[n], mask[n], outside, shape, dx, sigma_prime, radius, fit, acc[n], rho[n], gf[n],
                           gq[n], gp[n], gmask[n], gacc[n])


class OutsidePressureForce(torch.autograd.Function):
    """f [B, S, 2] = -p_k a_k (ibm.ibm_force with weight "outside", area "chord", no traction) in
    q's dtype from the surface polyline q [B, S, 2] (m) or, with ``surface`` [S] (numpy), the mesh
    nodes q [B, N, 2] of which those make it, the pressure p and mask b [B, 1, H, W] (Pa, 1) on the
    grid (H, W) of cells dx (m), the mask level above which cells are not sampled (``outside``,
    ibm.OUTSIDE_MASK), the kernel variance sigma_prime (m^2) and window radius (cells), and the
    fit: ``MEAN_FIT``, ``LINEAR_FIT`` or ``WALL_FIT``, the last with the nodes' accelerations acc
    (shaped as q, m/s^2) and the fluid's density rho [B] (kg/m^3; a constant here); CPU tensors.
    Differentiable in q, p, b and acc."""

    @staticmethod
    def arrays(q: Tensor, p: Tensor, b: Tensor, surface: np.ndarray | None, acc: Tensor | None, rho: np.ndarray,
               settings: tuple) -> tuple:
        """The kernels' arguments: a float64 copy of the polyline's nodes, p and b as flat arrays
        [B, H W] in their own dtype (a float32 value reads exactly into the float64 arithmetic:
        no copies of two whole grids), then the settings, the polyline's accelerations (float64,
        [B, S, 2]; zeros of one node without the wall fit) and rho."""
        B, H, W = p.shape[0], p.shape[-2], p.shape[-1]
        acc = np.zeros((B, 1, 2)) if acc is None else _surface_f64(acc, surface)
        return _surface_f64(q, surface), _flat_grid(p, B, H * W), _flat_grid(b, B, H * W), *settings, acc, rho

    @staticmethod
    def forward(ctx, q: Tensor, p: Tensor, b: Tensor, surface: np.ndarray | None, outside: float, dx: float,
                sigma_prime: float, radius: int, fit: int, acc: Tensor | None = None, rho: Tensor | float = 0.0):
        wall = fit == WALL_FIT
        if wall and (acc is None or torch.is_tensor(rho) and rho.requires_grad):
            raise ValueError("the IBM's wall fit needs wall=(the nodes' accelerations, a constant rho)")
        settings = (float(outside), (p.shape[-2], p.shape[-1]), float(dx), float(sigma_prime), int(radius), int(fit))
        B = p.shape[0]          # rho [B] float64 (read only by the wall fit)
        rho = np.broadcast_to(_f64(torch.as_tensor(rho)).reshape(-1), (B,)).copy() if wall else np.zeros(B)
        acc = acc if wall else None
        args = OutsidePressureForce.arrays(q, p, b, surface, acc, rho, settings)
        f = np.empty(args[0].shape)
        _each_fish(_fish_ibm, _ibm_parallel, *args, f, split=_ibm_split)
        # the tensors, not their float64 copies (two whole grids a frame), wait for the backward
        ctx.save_for_backward(q, p, b, acc)
        ctx.surface, ctx.settings, ctx.rho = surface, settings, rho
        return torch.from_numpy(f).to(q.dtype)

    @staticmethod
    def backward(ctx, gf: Tensor):
        q_in, p_in, b_in, acc_in = ctx.saved_tensors
        args = OutsidePressureForce.arrays(q_in, p_in, b_in, ctx.surface, acc_in, ctx.rho, ctx.settings)
        qs, p, acc = args[0], args[1], args[-2]
        gqs, gp, gmask, gacc = np.zeros(qs.shape), np.zeros(p.shape), np.zeros(p.shape), np.zeros(acc.shape)
        _each_fish(_fish_ibm_backward, _ibm_backward_parallel, *args, _f64(gf), gqs, gp, gmask, gacc)
        H, W = args[4]
        g_acc = None if acc_in is None else torch.from_numpy(_on_nodes(gacc, ctx.surface, acc_in.shape)).to(acc_in.dtype)
        return (torch.from_numpy(_on_nodes(gqs, ctx.surface, q_in.shape)).to(q_in.dtype),
                torch.from_numpy(gp).to(p_in.dtype).view(-1, 1, H, W),
                torch.from_numpy(gmask).to(b_in.dtype).view(-1, 1, H, W), None, None, None, None, None, None,
                g_acc, None)
