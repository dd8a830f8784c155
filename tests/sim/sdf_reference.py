"""Reference Psi: the original (pre-optimisation) implementation of ``nemsim.sim.sdf``, kept verbatim as the
oracle for tests/sim/test_sdf_fast.py. Not used by the package. Its design notes are in ``nemsim.sim.sdf``."""

from __future__ import annotations

import math

import numba
import numpy as np
from scipy import ndimage

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
def _is_band(g: np.ndarray, level: float, i: int, j: int, k: int) -> bool:
    """Voxel (i, j, k) has a 6-neighbour on the other side of ``level``."""
    nx, ny, nz = g.shape
    inside = g[i, j, k] > level
    if i > 0 and (g[i - 1, j, k] > level) != inside:
        return True
    if i < nx - 1 and (g[i + 1, j, k] > level) != inside:
        return True
    if j > 0 and (g[i, j - 1, k] > level) != inside:
        return True
    if j < ny - 1 and (g[i, j + 1, k] > level) != inside:
        return True
    if k > 0 and (g[i, j, k - 1] > level) != inside:
        return True
    if k < nz - 1 and (g[i, j, k + 1] > level) != inside:
        return True
    return False


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


@numba.njit(cache=True)
def closest_point_sdf(g: np.ndarray, level: float, max_dist: float, n_sweeps: int = 1) -> np.ndarray:
    """Signed distance (voxels, negative where g > level) to the ``level`` isosurface of g.

    Args:
      g: (X, Y, Z) float64 smooth indicator. level: isovalue. max_dist: distances are capped here
        (voxels without a closest point within reach get +/- max_dist). n_sweeps: forward+backward
        sweep pairs (1 is enough for the interfaces of this simulator; see tests/sim/test_sdf.py).
    Returns: (X, Y, Z) float64.
    """
    nx, ny, nz = g.shape
    big = 1e30
    d2 = np.full((nx, ny, nz), big)  # squared distance to the current closest point
    cp = np.empty((nx, ny, nz, 6))  # closest point (0:3) and the isosurface normal there (3:6)
    # 1) band: sign change to a 6-neighbour -> projection onto the isosurface
    lo_i, lo_j, lo_k = nx, ny, nz
    hi_i, hi_j, hi_k = -1, -1, -1
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if not _is_band(g, level, i, j, k):
                    continue
                lo_i = min(lo_i, i)
                hi_i = max(hi_i, i)
                lo_j = min(lo_j, j)
                hi_j = max(hi_j, j)
                lo_k = min(lo_k, k)
                hi_k = max(hi_k, k)
                px, py, pz = _project(g, level, i, j, k)
                d2[i, j, k] = (px - i) ** 2 + (py - j) ** 2 + (pz - k) ** 2
                cp[i, j, k, 0] = px
                cp[i, j, k, 1] = py
                cp[i, j, k, 2] = pz
                _, gx, gy, gz = _trilinear(g, px, py, pz)
                gn = math.sqrt(gx * gx + gy * gy + gz * gz) + 1e-300
                cp[i, j, k, 3] = gx / gn
                cp[i, j, k, 4] = gy / gn
                cp[i, j, k, 5] = gz / gn
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
                    for kk in range(k0, k1 + 1):
                        k = kk if direction == 0 else k1 - (kk - k0)
                        best = d2[i, j, k]
                        ba = -1
                        bb = -1
                        bc = -1
                        for o in range(13):
                            # the 13 offsets (di, dj, dk) lexicographically before (0, 0, 0)
                            di = o // 9 - 1
                            dj = (o // 3) % 3 - 1
                            dk = o % 3 - 1
                            a = i + sgn * di
                            b = j + sgn * dj
                            c = k + sgn * dk
                            if a < 0 or a >= nx or b < 0 or b >= ny or c < 0 or c >= nz:
                                continue
                            if d2[a, b, c] >= limit2:
                                continue
                            d = (cp[a, b, c, 0] - i) ** 2 + (cp[a, b, c, 1] - j) ** 2
                            d += (cp[a, b, c, 2] - k) ** 2
                            if d < best - 1e-12:
                                best = d
                                ba = a
                                bb = b
                                bc = c
                        if ba >= 0:
                            d2[i, j, k] = best
                            for q in range(6):
                                cp[i, j, k, q] = cp[ba, bb, bc, q]
    # 3) sub-sample correction: the nearest seed is up to ~half a voxel off the true foot point along the
    #    surface; remove up to H^2 of the tangential offset (exact for planes, continuous everywhere)
    h2 = 0.75 * 0.75
    cap2 = max_dist * max_dist
    out = np.empty((nx, ny, nz))
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                dd = d2[i, j, k]
                if dd < cap2:
                    rx = i - cp[i, j, k, 0]
                    ry = j - cp[i, j, k, 1]
                    rz = k - cp[i, j, k, 2]
                    dn = rx * cp[i, j, k, 3] + ry * cp[i, j, k, 4] + rz * cp[i, j, k, 5]
                    t2 = max(dd - dn * dn, 0.0)
                    d = math.sqrt(max(dd - min(t2, h2), 0.0))
                else:
                    d = max_dist
                out[i, j, k] = -d if g[i, j, k] > level else d
    return out


def smoothed_indicator(frac: np.ndarray, sigma: float, pad: int = 1) -> np.ndarray:
    """Padded, smoothed indicator g (nx + 2 pad, ny + 2 pad, nz + 2 pad) float64 of a fraction field.

    Args: frac (nx, ny, nz) fill fraction in [0, 1]; sigma: Gaussian width in voxels (0 = none).
    Periodic in x, y; replicated at the bottom and top in z.
    """
    f = np.pad(frac.astype(np.float64), ((pad, pad), (pad, pad), (0, 0)), mode="wrap")
    f = np.pad(f, ((0, 0), (0, 0), (pad, pad)), mode="edge")
    if sigma > 0:
        f = ndimage.gaussian_filter(f, sigma, mode=("wrap", "wrap", "nearest"), truncate=3.0)
    return f


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
        phi = signed_distance(frac, sigma, d_max + 1.0)  # (X, Y, Z)
        out[c] = np.clip(phi / d_max, -1.0, 1.0).transpose(2, 1, 0)
    return out
