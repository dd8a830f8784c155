"""Psi: microscopic voxel state -> the two normalized signed-distance channels ([supp_representation]).

The paper's simulator hands material changes to a level-set solver; its Psi is not disclosed. Ours maps
the per-voxel fill fraction of each channel straight to a sub-voxel-accurate signed distance:

1. fraction f (mask: resist; Si: Si + SiCl_x), padded by one voxel (periodic in x, y; replicated in z);
2. indicator g = Gaussian(f, sigma = ``psi_sigma_vox``) (periodic in x, y), interface = {g = 1/2}. For a
   planar interface the 1/2 level of the smoothed volume fraction sits exactly at the true interface, so
   partial voxels give sub-voxel positions; the smoothing also removes voxel-scale Monte Carlo roughness;
3. closest points: every voxel with a sign change to a 6-neighbour ("band") is projected onto the
   1/2-isosurface of the trilinear interpolant of g by Newton steps along the gradient (Chopp-style
   closest-point initialisation); the closest points are then propagated to all voxels by forward and
   backward raster sweeps over the 26-neighbourhood (a vector distance transform with sub-voxel seeds);
4. phi = +/- |x - closest point| (negative inside, where g > 1/2), in voxels (lattice units);
5. normalized channel = clip(phi / d_max, -1, 1) [eq:supp_sdf_normalization], transposed (x,y,z) ->
   (z,y,x) [eq:supp_axis_transposition], float32.

|grad phi| = 1 up to the propagation's second-order error (checked on a sphere in tests/sim/test_sim_sdf.py).
Choices where the paper is silent: sigma, the one-voxel padding (the distance transform is not periodic;
the domain edges are flat resist/Si far from the opening), Newton projection (4 steps, step <= 1 voxel).

Speed (Psi runs 101 times per trajectory): the smoothing and the closest-point transform are single numba
kernels that write the clipped, transposed float32 state directly, over reused work buffers with a sentinel
shell; the arithmetic, visiting order and tie-breaking are those of the straightforward loops, bit for bit
(tests/sim/test_sdf_fast.py). Not recomputing unchanged regions: the sweeps carry closest points along whole
rows, and between snapshots the indicator changes all over the surface, so little would be saved.
"""

from __future__ import annotations

import math
import threading

import numba
import numpy as np

from nemsim.scenes import Scene

LEVEL = 0.5


@numba.njit(cache=True)
def _trilinear(g: np.ndarray, px: float, py: float, pz: float) -> tuple[float, float, float, float]:
    """Value and gradient of the trilinear interpolant of g (index coordinates, clamped to the box)."""
    nx, ny, nz = g.shape
    px = min(max(px, 0.0), nx - 1.000001)
    py = min(max(py, 0.0), ny - 1.000001)
    pz = min(max(pz, 0.0), nz - 1.000001)
    i = int(px)
    j = int(py)
    k = int(pz)
    fx = px - i
    fy = py - j
    fz = pz - k
    c000 = g[i, j, k]
    c100 = g[i + 1, j, k]
    c010 = g[i, j + 1, k]
    c110 = g[i + 1, j + 1, k]
    c001 = g[i, j, k + 1]
    c101 = g[i + 1, j, k + 1]
    c011 = g[i, j + 1, k + 1]
    c111 = g[i + 1, j + 1, k + 1]
    c00 = c000 + (c100 - c000) * fx
    c10 = c010 + (c110 - c010) * fx
    c01 = c001 + (c101 - c001) * fx
    c11 = c011 + (c111 - c011) * fx
    c0 = c00 + (c10 - c00) * fy
    c1 = c01 + (c11 - c01) * fy
    val = c0 + (c1 - c0) * fz
    dz = c1 - c0
    dy = (c10 - c00) * (1.0 - fz) + (c11 - c01) * fz
    dx0 = (c100 - c000) * (1.0 - fy) + (c110 - c010) * fy
    dx1 = (c101 - c001) * (1.0 - fy) + (c111 - c011) * fy
    dx = dx0 * (1.0 - fz) + dx1 * fz
    return val, dx, dy, dz


@numba.njit(cache=True)
def _project(g: np.ndarray, level: float, i: int, j: int, k: int) -> tuple[float, float, float]:
    """Closest point of voxel centre (i, j, k) on the ``level`` isosurface of the trilinear interpolant
    (Newton steps along the gradient, each at most one voxel; linear edge crossing as a fallback)."""
    nx, ny, nz = g.shape
    px = float(i)
    py = float(j)
    pz = float(k)
    ok = True
    for _ in range(6):
        val, gx, gy, gz = _trilinear(g, px, py, pz)
        g2 = gx * gx + gy * gy + gz * gz
        if g2 < 1e-14:
            ok = False
            break
        f = (val - level) / g2
        sx = f * gx
        sy = f * gy
        sz = f * gz
        sn = math.sqrt(sx * sx + sy * sy + sz * sz)
        if sn > 1.0:
            sx /= sn
            sy /= sn
            sz /= sn
        px -= sx
        py -= sy
        pz -= sz
        if sn < 1e-6:
            break
    if ok and (px - i) ** 2 + (py - j) ** 2 + (pz - k) ** 2 <= 2.25:
        return px, py, pz
    s = g[i, j, k] - level
    best = 1e30
    px = float(i)
    py = float(j)
    pz = float(k)
    for a in range(6):
        di = (a == 1) - (a == 0)
        dj = (a == 3) - (a == 2)
        dk = (a == 5) - (a == 4)
        ii = i + di
        jj = j + dj
        kk = k + dk
        if ii < 0 or ii >= nx or jj < 0 or jj >= ny or kk < 0 or kk >= nz:
            continue
        s2 = g[ii, jj, kk] - level
        if (s > 0.0) != (s2 > 0.0):
            t = s / (s - s2)
            if t < best:
                best = t
                px = i + t * di
                py = j + t * dj
                pz = k + t * dk
    return px, py, pz


# the 13 neighbour offsets (di, dj, dk) lexicographically before (0, 0, 0), in sweep-tie-breaking order
_PRED = np.array([(o // 9 - 1, (o // 3) % 3 - 1, o % 3 - 1) for o in range(13)], dtype=np.int64)  # (13, 3)


@numba.njit(cache=True)
def _sdf_kernel(
    g: np.ndarray, level: float, max_dist: float, n_sweeps: int, pred: np.ndarray, out: np.ndarray,
    scale: float, clip: bool, work: np.ndarray, inside: np.ndarray,
) -> None:
    """Closest-point signed distance phi of the ``level`` isosurface of g (``closest_point_sdf``), written
    as ``out[i, j, k] = phi / scale``, clipped to [-1, 1] if ``clip`` (out may be any float view).

    Work arrays carry a one-voxel sentinel shell (squared distance +inf) and flat indices, so the sweeps
    need no bounds tests; the visiting order, the neighbour order and the comparisons are those of the
    straightforward loop (tests/sim/sdf_reference.py), so the result is the same to the last bit.
    """
    nx, ny, nz = g.shape
    sy = nz + 2  # flat strides of the (nx + 2, ny + 2, nz + 2) work arrays
    sx = (ny + 2) * sy
    big = 1e30
    w = work  # per work voxel: squared distance to the current closest point, the closest point (index
    w[:, 0] = big  # coordinates of g) and the isosurface normal there; one cache line per voxel
    offs = np.empty(13, dtype=np.int64)
    for o in range(13):
        offs[o] = pred[o, 0] * sx + pred[o, 1] * sy + pred[o, 2]
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                inside[i, j, k] = g[i, j, k] > level
    # 1) band: sign change to a 6-neighbour -> projection onto the isosurface
    lo_i, lo_j, lo_k = nx, ny, nz
    hi_i, hi_j, hi_k = -1, -1, -1
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                c = inside[i, j, k]
                if not (
                    (i > 0 and inside[i - 1, j, k] != c)
                    or (i < nx - 1 and inside[i + 1, j, k] != c)
                    or (j > 0 and inside[i, j - 1, k] != c)
                    or (j < ny - 1 and inside[i, j + 1, k] != c)
                    or (k > 0 and inside[i, j, k - 1] != c)
                    or (k < nz - 1 and inside[i, j, k + 1] != c)
                ):
                    continue
                lo_i = min(lo_i, i)
                hi_i = max(hi_i, i)
                lo_j = min(lo_j, j)
                hi_j = max(hi_j, j)
                lo_k = min(lo_k, k)
                hi_k = max(hi_k, k)
                px, py, pz = _project(g, level, i, j, k)
                p = (i + 1) * sx + (j + 1) * sy + (k + 1)
                w[p, 0] = (px - i) ** 2 + (py - j) ** 2 + (pz - k) ** 2
                w[p, 1] = px
                w[p, 2] = py
                w[p, 3] = pz
                _, gx, gy, gz = _trilinear(g, px, py, pz)
                gn = math.sqrt(gx * gx + gy * gy + gz * gz) + 1e-300
                w[p, 4] = gx / gn
                w[p, 5] = gy / gn
                w[p, 6] = gz / gn
    # 2) propagate closest points: forward and backward raster sweeps, each over the 13 neighbours that
    #    precede the voxel in its sweep order (vector distance transform), restricted to the box of
    #    voxels within reach of the band (others end up clipped at max_dist anyway)
    reach = int(math.ceil(max_dist)) + 2
    limit2 = (max_dist + 2.0) ** 2
    i0, i1 = max(lo_i - reach, 0), min(hi_i + reach, nx - 1)
    j0, j1 = max(lo_j - reach, 0), min(hi_j + reach, ny - 1)
    k0, k1 = max(lo_k - reach, 0), min(hi_k + reach, nz - 1)
    for _sweep in range(n_sweeps if hi_i >= 0 else 0):
        for direction in range(2):
            sgn = 1 if direction == 0 else -1
            for ii in range(i0, i1 + 1):
                i = ii if direction == 0 else i1 - (ii - i0)
                for jj in range(j0, j1 + 1):
                    j = jj if direction == 0 else j1 - (jj - j0)
                    base = (i + 1) * sx + (j + 1) * sy + 1
                    for kk in range(k0, k1 + 1):
                        k = kk if direction == 0 else k1 - (kk - k0)
                        p = base + k
                        best = w[p, 0]
                        bq = -1
                        for o in range(13):
                            q = p + sgn * offs[o]
                            if w[q, 0] >= limit2:  # also the sentinel shell
                                continue
                            d = (w[q, 1] - i) ** 2 + (w[q, 2] - j) ** 2
                            d += (w[q, 3] - k) ** 2
                            if d < best - 1e-12:
                                best = d
                                bq = q
                        if bq >= 0:
                            w[p, 0] = best
                            for f in range(1, 7):
                                w[p, f] = w[bq, f]
    # 3) sub-sample correction: the nearest seed is up to ~half a voxel off the true foot point along the
    #    surface; remove up to H^2 of the tangential offset (exact for planes, continuous everywhere)
    h2 = 0.75 * 0.75
    cap2 = max_dist * max_dist
    for i in range(nx):
        for j in range(ny):
            base = (i + 1) * sx + (j + 1) * sy + 1
            for k in range(nz):
                p = base + k
                dd = w[p, 0]
                if dd < cap2:
                    rx = i - w[p, 1]
                    ry = j - w[p, 2]
                    rz = k - w[p, 3]
                    dn = rx * w[p, 4] + ry * w[p, 5] + rz * w[p, 6]
                    t2 = max(dd - dn * dn, 0.0)
                    d = math.sqrt(max(dd - min(t2, h2), 0.0))
                else:
                    d = max_dist
                v = (-d if g[i, j, k] > level else d) / scale
                out[i, j, k] = min(max(v, -1.0), 1.0) if clip else v


_local = threading.local()


def _workspace(shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Reusable kernel buffers for a g of this shape, one set per thread: ((X+2)(Y+2)(Z+2), 8) float64
    (squared distance, closest point, normal; with a sentinel shell) and (X, Y, Z) bool (inside)."""
    cached = getattr(_local, "work", None)
    if cached is None or cached[1].shape != shape:
        n_work = (shape[0] + 2) * (shape[1] + 2) * (shape[2] + 2)
        cached = (np.empty((n_work, 8)), np.empty(shape, dtype=np.bool_))
        _local.work = cached
    return cached


def closest_point_sdf(g: np.ndarray, level: float, max_dist: float, n_sweeps: int = 1) -> np.ndarray:
    """Signed distance (voxels, negative where g > level) to the ``level`` isosurface of g.

    Args:
      g: (X, Y, Z) float64 smooth indicator. level: isovalue. max_dist: distances are capped here
        (voxels without a closest point within reach get +/- max_dist). n_sweeps: forward+backward
        sweep pairs (1 is enough for the interfaces of this simulator; see tests/sim/test_sim_sdf.py).
    Returns: (X, Y, Z) float64.
    """
    out = np.empty(g.shape)
    _sdf_kernel(g, float(level), float(max_dist), int(n_sweeps), _PRED, out, 1.0, False, *_workspace(g.shape))
    return out


def _gaussian_weights(sigma: float) -> np.ndarray:
    """Half of the normalized Gaussian kernel, w[m] for offsets m = 0..r, r = int(3 sigma + 0.5) (the
    kernel of scipy.ndimage.gaussian_filter with truncate=3, computed the same way)."""
    r = int(3.0 * sigma + 0.5)
    x = np.arange(-r, r + 1)
    w = np.exp(-0.5 / (sigma * sigma) * x**2)
    return (w / w.sum())[r:]


@numba.njit(cache=True)
def _smooth_kernel(frac: np.ndarray, pad: int, w: np.ndarray) -> np.ndarray:
    """Pad (wrap in x, y; edge in z) and smooth separably along x, y, z (periodic over the padded extent in
    x, y; nearest in z); empty w = no smoothing. Sums in the order of scipy's symmetric correlate1d
    (centre first, then the outermost pair inwards), so the result matches gaussian_filter bit for bit."""
    nx0, ny0, nz0 = frac.shape
    nx, ny, nz = nx0 + 2 * pad, ny0 + 2 * pad, nz0 + 2 * pad
    f = np.empty((nx, ny, nz))
    for i in range(nx):
        a = (i - pad) % nx0
        for j in range(ny):
            b = (j - pad) % ny0
            for k in range(nz):
                f[i, j, k] = frac[a, b, min(max(k - pad, 0), nz0 - 1)]
    r = len(w) - 1
    if r < 0:
        return f
    h = np.empty_like(f)
    xl = np.empty((r + 1, nx), dtype=np.int64)  # wrapped neighbour indices (periodic over the padded extent)
    xr = np.empty((r + 1, nx), dtype=np.int64)
    yl = np.empty((r + 1, ny), dtype=np.int64)
    yr = np.empty((r + 1, ny), dtype=np.int64)
    for m in range(r + 1):
        for i in range(nx):
            xl[m, i] = (i - m) % nx
            xr[m, i] = (i + m) % nx
        for j in range(ny):
            yl[m, j] = (j - m) % ny
            yr[m, j] = (j + m) % ny
    # the same per-element sums as scipy, accumulated one offset at a time along contiguous z rows
    for i in range(nx):  # along x (wrap)
        for j in range(ny):
            for k in range(nz):
                h[i, j, k] = f[i, j, k] * w[0]
            for m in range(r, 0, -1):
                a, b, wm = xl[m, i], xr[m, i], w[m]
                for k in range(nz):
                    h[i, j, k] += (f[a, j, k] + f[b, j, k]) * wm
    for i in range(nx):  # along y (wrap)
        for j in range(ny):
            for k in range(nz):
                f[i, j, k] = h[i, j, k] * w[0]
            for m in range(r, 0, -1):
                a, b, wm = yl[m, j], yr[m, j], w[m]
                for k in range(nz):
                    f[i, j, k] += (h[i, a, k] + h[i, b, k]) * wm
    for i in range(nx):  # along z (nearest)
        for j in range(ny):
            for k in range(nz):
                h[i, j, k] = f[i, j, k] * w[0]
            for m in range(r, 0, -1):
                wm = w[m]
                for k in range(nz):
                    h[i, j, k] += (f[i, j, max(k - m, 0)] + f[i, j, min(k + m, nz - 1)]) * wm
    return h


def smoothed_indicator(frac: np.ndarray, sigma: float, pad: int = 1) -> np.ndarray:
    """Padded, smoothed indicator g (nx + 2 pad, ny + 2 pad, nz + 2 pad) float64 of a fraction field.

    Args: frac (nx, ny, nz) fill fraction in [0, 1]; sigma: Gaussian width in voxels (0 = none).
    Periodic in x, y; replicated at the bottom and top in z.
    """
    w = _gaussian_weights(sigma) if sigma > 0 else np.empty(0)
    return _smooth_kernel(np.ascontiguousarray(frac), int(pad), w)


def signed_distance(frac: np.ndarray, sigma: float, max_dist: float, pad: int = 1) -> np.ndarray:
    """Padded signed distance (voxels, negative inside) of a fraction field, (nx+2, ny+2, nz+2) float64."""
    g = smoothed_indicator(frac, sigma, pad)
    return closest_point_sdf(g, LEVEL, float(max_dist))


def psi(mask_frac: np.ndarray, si_frac: np.ndarray, scene: Scene, sigma: float) -> np.ndarray:
    """Psi: (mask, Si) fractions, each (nx, ny, nz) -> normalized state (2, D, H, W) float32.

    D = nz + 2, H = ny + 2, W = nx + 2 (padded, transposed (x,y,z) -> (z,y,x)); values in [-1, 1].
    """
    d_max = scene.d_max_vox
    out = np.empty(scene.state_shape, dtype=np.float32)
    for c, frac in enumerate((mask_frac, si_frac)):
        g = smoothed_indicator(frac, sigma)  # (X, Y, Z)
        view = out[c].transpose(2, 1, 0)  # (X, Y, Z) view of the (Z, Y, X) channel
        _sdf_kernel(g, LEVEL, d_max + 1.0, 1, _PRED, view, d_max, True, *_workspace(g.shape))
    return out
