"""Profile metrics of an etched feature (hole or trench), in nm, from a normalized SDF state and its Scene.

The paper names the morphology quantities (etch depth, top-opening width, neck width, bottom width, bowing;
[supp_protocols] "Selection of OOD Control Axes") but does not define them; DESIGN.md adds mask thickness
loss. Our definitions follow.

Coordinates: a state is (2, D, H, W) = (channel, z, y, x) padded by one voxel (index = native + 1); a native
voxel spans ±0.5 around its integer centre, so the initial Si top is at native z = si_top - 0.5 and the
resist top at resist_top - 0.5. SDFs are negative inside material (channel 0 mask, 1 Si). The hole axis is
``scene.opening_centre`` (the field is interpolated onto it between voxel centres); zero crossings are
located sub-voxel by linear interpolation, and a sample equal to 0 counts as material.

Definitions (nm = voxels * scene.voxel_nm):
  * ``etch_depth``: initial Si top minus the hole floor, the first vacuum->Si crossing on the hole axis
    scanning down from the top of the box (0 unetched, the full Si thickness if the axis holds no Si).
  * width w(z): on the Si channel, along the x and y lines through the axis, the distance between the
    first vacuum->Si crossings walking outward on either side (the domain edge if none); mean of the two.
  * ``top_width``: w at the top Si row (native z = si_top - 1).
  * ``bowing``: the largest excess of a row's width over the narrowest row above it (bow CD minus neck
    CD), over the Si rows above the floor at least ``BOW_SKIP_ROWS`` = 2 below the top Si row; >= 0. The
    top rows are skipped because Psi's smoothing rounds the Si/resist corner, so they read wider than their
    voxels and would hide a bulge just below the mask (benchmarks/small/bowing.md).
  * ``neck_width``: the narrowest row above the bow (the reference of ``bowing``).
  * ``bottom_width``: w at h_b = max(0.1 * etch_depth, 1 voxel) above the floor (interpolated between rows,
    capped at the top Si row); 0 when the hole is less than one voxel deep.
  * ``mask_loss``: initial resist top minus the mean height of the mask top (first vacuum->mask crossing
    per column) over the planar field, the columns at least opening_radius + d_max from the axis (else all
    outside opening_radius + 1); a column without mask counts as fully eroded.

Where a width is a measurement: on a row of sidewall, at least h_b above the floor (the rows below belong
to the rounded floor, which is why ``bottom_width`` is taken h_b up). ``measured_profile_metrics`` reports
NaN until then: ``top_width`` and ``bottom_width`` until the top Si row is sidewall (a hole 1.5 voxels
deep), ``neck_width`` and ``bowing`` until the first reference row is (3.5 voxels). The neck is the
narrowest row above the bow, and the bow row is wherever the widening peaks, so when a faint bulge appears
lower down the neck moves to another row and its width jumps; ``neck_depth`` (nm below the initial Si top)
names the row the neck was measured on, so a jump of ``neck_width`` shows as a change of ``neck_depth``.
``profile_metrics_batch`` gives a number at every step, which searches and losses need; where a metric is
undefined that number stands in for it (0, a width of the rounded floor, or for the neck the top width).

Trenches (``scene.kind == "trench"``, a per-case scene from ``nemsim.geometry.feature``): the metrics read
the state's mean over y (the line's direction, its mean profile: a 3-D simulator's noise along the line
averages out; a cross-section's state is already y-invariant); widths are across x only (the x line through
the axis), and mask_loss's planar field is the columns at least opening half-width + d_max from the axis
(else outside half-width + 1). Every metric reads the case's own scene (its Si top, mask top, opening). A
trench's states may be given as that mean profile already, (T, 2, D, 1, W) (a cross-section model's line,
``Predictor.metrics``): the same metrics without a full field.

Both are vectorized over a leading step axis (T, 2, D, H, W). They also take the
states' quadrant (T, 2, D, c, c) (``nemsim.symmetry.fold``) of fields exactly symmetric under the square's
mirrors (a quarter-domain model's rollout): the lines through the axis and the mask-top map are rebuilt by
reflection from the quadrant, so the metrics equal those of the unfolded fields without building them.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numba
import numpy as np

if TYPE_CHECKING:
    from nemsim.scenes import Scene

METRIC_NAMES = ("etch_depth", "top_width", "neck_width", "bottom_width", "bowing", "mask_loss")
BOTTOM_FRACTION = 0.1  # bottom width measured this fraction of the etch depth above the floor
BOTTOM_MIN_VOX = 1.0  # ... but at least this many voxels above it
BOW_SKIP_ROWS = 2  # rows below the top Si row where bowing's reference starts (corner rounding, see above)


@numba.njit(cache=True, nogil=True)
def _first_crossings(values: np.ndarray, pos: np.ndarray, out: np.ndarray) -> None:
    """out[i] = the first vacuum->material crossing of the line values[i] (K, M) at coordinates pos (M,)."""
    m = values.shape[1]
    edge = pos[m - 1] + 0.5 * (pos[m - 1] - pos[m - 2])
    for i in range(values.shape[0]):
        row = values[i]
        k = 0
        while k < m and not row[k] <= 0.0:  # NaN is no material, as in the comparison
            k += 1
        if k == m:
            out[i] = edge
        elif k == 0:
            out[i] = pos[0]
        else:
            v0 = np.float64(row[k - 1])  # last vacuum sample (> 0)
            v1 = np.float64(row[k])  # first material sample (<= 0)
            frac = v0 / (v0 - v1) if v0 - v1 > 0 else 0.0
            out[i] = pos[k - 1] + frac * (pos[k] - pos[k - 1])


@numba.njit(cache=True, nogil=True)
def _first_crossings_columns(values: np.ndarray, pos: np.ndarray, out: np.ndarray) -> None:
    """out[t, j] = the first vacuum->material crossing of the column values[t, :, j] (T, M, K), any strides,
    at coordinates pos (M,): `_first_crossings` without a contiguous copy of the columns."""
    m = values.shape[1]
    edge = pos[m - 1] + 0.5 * (pos[m - 1] - pos[m - 2])
    for t in range(values.shape[0]):
        for j in range(values.shape[2]):
            k = 0
            while k < m and not values[t, k, j] <= 0.0:  # NaN is no material, as in the comparison
                k += 1
            if k == m:
                out[t, j] = edge
            elif k == 0:
                out[t, j] = pos[0]
            else:
                v0 = np.float64(values[t, k - 1, j])
                v1 = np.float64(values[t, k, j])
                frac = v0 / (v0 - v1) if v0 - v1 > 0 else 0.0
                out[t, j] = pos[k - 1] + frac * (pos[k] - pos[k - 1])


def _first_crossing(values: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Position of the first vacuum->material crossing scanning along the last axis.

    Args:
        values: (..., M) SDF samples in scan order (any float dtype and strides).
        pos: (M,) their coordinates (monotone, equally spaced, M >= 2).
    Returns:
        (...) float64 crossing coordinate: pos[0] if the first sample is material; half a step beyond pos[-1]
        (the domain edge) if no sample is material; else linear interpolation of the zero crossing (in
        float64). One compiled pass over the lines (the vectorized form made several full-size temporaries).
    """
    lines = np.ascontiguousarray(values).reshape(-1, values.shape[-1])
    out = np.empty(lines.shape[0], dtype=np.float64)
    _first_crossings(lines, np.ascontiguousarray(pos, dtype=np.float64), out)
    return out.reshape(values.shape[:-1])


def _interp_at(field: np.ndarray, axis: int, at: float) -> np.ndarray:
    """field sampled at a (possibly half-integer) index along ``axis`` by linear interpolation (an axis of
    size 1 is a field constant along it: a trench's line profile across y)."""
    lo = int(math.floor(at))
    w = at - lo
    axis = axis % field.ndim

    def plane(i: int) -> np.ndarray:  # a view (np.take would copy the whole, possibly strided, field first)
        return field[(slice(None),) * axis + (i,)]

    if field.shape[axis] == 1:
        return plane(0).astype(np.float64)

    a = plane(lo).astype(np.float64)
    if w < 1e-9:
        return a
    return (1.0 - w) * a + w * plane(lo + 1)


@numba.njit(cache=True, nogil=True)
def _crossing_from_axis(row: np.ndarray, centre: float, a: float, start: int, step: int, count: int) -> float:
    """`_first_crossings` of one line walking outward from the axis: the samples centre (at a), then
    row[start], row[start + step], ... (count of them, at their indices), without building the line."""
    m = count + 1
    p_last = a if count == 0 else float(start + (count - 1) * step)
    p_prev = a if count <= 1 else float(start + (count - 2) * step)  # count 0: the edge is at a
    k = 0
    while k < m:
        v = centre if k == 0 else np.float64(row[start + (k - 1) * step])
        if v <= 0.0:
            break
        k += 1
    if k == m:
        return p_last + 0.5 * (p_last - p_prev)
    if k == 0:
        return a
    v0 = centre if k == 1 else np.float64(row[start + (k - 2) * step])
    v1 = np.float64(row[start + (k - 1) * step])
    p0 = a if k == 1 else float(start + (k - 2) * step)
    p1 = float(start + (k - 1) * step)
    frac = v0 / (v0 - v1) if v0 - v1 > 0 else 0.0
    return p0 + frac * (p1 - p0)


@numba.njit(cache=True, nogil=True)
def _half_widths_lines(
    lines: np.ndarray, a: float, lo: int, w: float, r0: int, l0: int, n: int, out: np.ndarray
) -> None:
    """`_half_widths` of the lines (K, n + 2) float64 into out (K,): one compiled pass, no temporaries."""
    for i in range(lines.shape[0]):
        row = lines[i]
        centre = row[lo] if w < 1e-9 else (1.0 - w) * row[lo] + w * row[lo + 1]
        right = _crossing_from_axis(row, centre, a, r0, 1, max(n + 1 - r0, 0))
        left = _crossing_from_axis(row, centre, a, l0, -1, max(l0, 0))
        out[i] = (right - a) + (a - left)


def _half_widths(lines: np.ndarray, a: float, n: int) -> np.ndarray:
    """Sum of the outward distances from the axis to the first crossing on each side, in voxels.

    Args:
        lines: (..., n + 2) padded lines (native samples at indices 1..n).
        a: axis position in index coordinates.
    Returns:
        (...) width in voxels (0 where the axis sample is material). The axis sample is interpolated
        between its neighbours (`_interp_at`), then each side is scanned outward from it to the domain
        edge (`_first_crossings`), in one compiled pass (the lines built by concatenation made temporaries
        of every line).
    """
    lo = int(math.floor(a))
    flat = np.ascontiguousarray(lines, dtype=np.float64).reshape(-1, lines.shape[-1])
    out = np.empty(flat.shape[0], dtype=np.float64)
    r0 = int(math.floor(a)) + 1  # first native index strictly right of a
    l0 = int(math.ceil(a)) - 1  # first native index strictly left of a
    _half_widths_lines(flat, float(a), lo, float(a - lo), r0, l0, n, out)
    return out.reshape(lines.shape[:-1])


def _reflect(half: np.ndarray, n: int) -> np.ndarray:
    """The full line (..., n) rebuilt from its lower half (..., c) by the mirror about the centre."""
    c = half.shape[-1]
    return np.concatenate([half, half[..., : n - c][..., ::-1]], axis=-1)


def _widths(si: np.ndarray, scene: Scene, quadrant: bool = False) -> np.ndarray:
    """Width w (voxels) of every row. si: (T, D, H, W), or its quadrant (T, D, c, c) -> (T, D)."""
    ax_x = scene.opening_centre[0] + 1.0  # index coordinates
    ax_y = scene.opening_centre[1] + 1.0
    if quadrant:  # the axis lies on the quadrant's last row and column (the mirror of each is its neighbour)
        x_lines = _reflect(si[..., -1, :].astype(np.float64), scene.nx + 2)  # (T, D, W)
        y_lines = _reflect(si[..., :, -1].astype(np.float64), scene.ny + 2)  # (T, D, H)
    else:
        x_lines = _interp_at(si, 2, ax_y)  # (T, D, W)
        if scene.kind == "trench":  # a line along y: its width is across x (module docstring)
            return _half_widths(x_lines, ax_x, scene.nx)
        y_lines = _interp_at(si, 3, ax_x)  # (T, D, H)
    return 0.5 * (_half_widths(x_lines, ax_x, scene.nx) + _half_widths(y_lines, ax_y, scene.ny))


def _field_columns_mask(scene: Scene) -> np.ndarray:
    """(ny, nx) bool: the planar mask region used for mask_loss."""
    cx, cy = scene.opening_centre
    y, x = np.mgrid[0 : scene.ny, 0 : scene.nx]
    r = np.abs(x - cx) if scene.kind == "trench" else np.hypot(x - cx, y - cy)
    sel = r >= scene.opening_radius_vox + scene.d_max_vox
    if not sel.any():
        sel = r > scene.opening_radius_vox + 1.0
    return sel


def _measure(states: Any, scene: Scene) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """(``profile_metrics_batch``'s metrics, the neck row's depth (T,) in voxels below the initial Si top)."""
    if hasattr(states, "detach"):
        states = states.detach().cpu().numpy()
    x = np.asarray(states)
    quadrant = scene.symmetry == "d4" and x.ndim == 5 and x.shape[1:] == scene.quarter_state_shape
    full = tuple(scene.state_shape)
    line = scene.kind == "trench" and x.ndim == 5 and x.shape[1:] == (*full[:2], 1, full[3])
    if not (quadrant or line) and (x.ndim != 5 or x.shape[1:] != scene.state_shape):
        raise ValueError(
            f"states shape {x.shape}; expected (T, *{scene.state_shape}) for scene {scene.name!r}"
        )
    if scene.kind == "trench":  # the line's mean profile (module docstring), (T, 2, D, 1, W)
        x = np.asarray(x if line else x.mean(axis=3, keepdims=True, dtype=np.float64), dtype=np.float32)
    # no float64 copy of the whole stack: only the extracted lines/columns are promoted
    t_count = x.shape[0]
    nz = scene.nz
    vox = scene.voxel_nm
    mask, si = x[:, 0], x[:, 1]  # (T, D, H, W)
    ax_x = scene.opening_centre[0] + 1.0
    ax_y = scene.opening_centre[1] + 1.0

    # --- etch depth: scan the axis column of the Si channel downward ---------------------------
    if quadrant:
        col = si[:, :, -1, -1].astype(np.float64)  # (T, D)
    else:
        col = _interp_at(_interp_at(si, 3, ax_x), 2, ax_y)  # (T, D)
    rows_down = np.arange(nz, 0, -1, dtype=np.float64)  # native rows, top to bottom (index coords)
    floor = _first_crossing(col[:, nz:0:-1], rows_down)  # (T,) index coordinate of the hole floor
    si_surface = scene.si_top + 0.5  # initial Si top in index coordinates
    depth = si_surface - floor  # (T,) voxels

    # --- width profile over the Si rows ---------------------------------------------------------
    top_row = scene.si_top  # index of the top Si row (native si_top - 1)
    w = _widths(si[:, 1 : top_row + 1], scene, quadrant)  # (T, top_row) rows 1..top_row
    rows = np.arange(1, top_row + 1, dtype=np.float64)
    above = rows[None, :] > floor[:, None]  # rows inside the hole
    top_w = w[:, -1]
    # rows from the first reference row downward (top to bottom), rows below the floor masked out
    ref = top_row - 1 - BOW_SKIP_ROWS  # column of the first reference row in w
    w_down = w[:, ref::-1] if ref >= 0 else w[:, :0]  # (T, ref + 1)
    in_hole = above[:, ref::-1] if ref >= 0 else above[:, :0]
    has_rows = in_hole.any(axis=1)
    neck_above = np.minimum.accumulate(np.where(in_hole, w_down, np.inf), axis=1)  # narrowest row so far
    excess = np.where(in_hole, w_down - neck_above, -np.inf)  # (T, ref + 1) widening over the neck
    k_bow = np.argmax(excess, axis=1) if excess.shape[1] else np.zeros(t_count, dtype=np.int64)
    bowing = np.where(has_rows, np.maximum(np.take_along_axis(excess, k_bow[:, None], 1)[:, 0], 0.0), 0.0)
    if excess.shape[1]:  # the neck: the narrowest in-hole row from the first reference row down to the bow
        upto_bow = np.arange(excess.shape[1])[None, :] <= k_bow[:, None]
        k_neck = np.argmin(np.where(in_hole & upto_bow, w_down, np.inf), axis=1)
        neck = np.where(has_rows, np.take_along_axis(w_down, k_neck[:, None], 1)[:, 0], top_w)
    else:
        k_neck, neck = k_bow, top_w
    neck_depth = BOW_SKIP_ROWS + 0.5 + k_neck  # voxels below the initial Si top (w_down[:, j]: row ref - j)

    # --- bottom width: interpolate the Si field to h_b above the floor --------------------------
    h_b = np.maximum(BOTTOM_FRACTION * depth, BOTTOM_MIN_VOX)
    z_b = np.clip(floor + h_b, 1.0, float(top_row))  # (T,) index coordinate
    lo = np.minimum(np.floor(z_b).astype(np.int64), top_row - 1)
    frac = (z_b - lo)[:, None, None]
    t_idx = np.arange(t_count)
    plane = (1.0 - frac) * si[t_idx, lo] + frac * si[t_idx, lo + 1]  # (T, H, W) float64
    bottom = _widths(plane[:, None], scene, quadrant)[:, 0]
    bottom = np.where(depth >= BOTTOM_MIN_VOX, bottom, 0.0)

    # --- mask thickness loss ---------------------------------------------------------------------
    sel = _field_columns_mask(scene)  # (ny, nx)
    m_rows = np.arange(nz, scene.si_top, -1, dtype=np.float64)
    if quadrant:  # the mask top of every quadrant column, reflected to the full map, then the same columns
        m_cols = mask[:, nz : scene.si_top : -1]  # (T, rows, c, c), rows top to bottom (a view)
        top_q = np.empty((t_count, m_cols.shape[2] * m_cols.shape[3]), dtype=np.float64)
        _first_crossings_columns(m_cols.reshape(t_count, m_cols.shape[1], -1), m_rows, top_q)
        top_q = top_q.reshape(t_count, *m_cols.shape[2:])  # (T, c, c)
        top_full = _reflect(np.swapaxes(_reflect(top_q, scene.nx + 2), 1, 2), scene.ny + 2)  # (T, W, H)
        m_top = np.swapaxes(top_full, 1, 2)[:, 1:-1, 1:-1][:, sel].mean(axis=1)  # (T,)
    elif scene.kind == "trench":  # the line's columns (sel is the same in every row of y)
        m_cols = mask[:, scene.si_top + 1 : nz + 1, 0, 1:-1][:, :, sel[0]]  # (T, rows, K) mask rows
        m_cols = np.moveaxis(m_cols[:, ::-1], 1, -1)  # (T, K, rows) top to bottom
        m_top = _first_crossing(m_cols, m_rows).mean(axis=1)  # (T,)
    else:
        m_cols = mask[:, scene.si_top + 1 : nz + 1, 1:-1, 1:-1][:, :, sel]  # (T, rows, K) mask rows
        m_cols = np.moveaxis(m_cols[:, ::-1], 1, -1)  # (T, K, rows) top to bottom
        m_top = _first_crossing(m_cols, m_rows).mean(axis=1)  # (T,)
    mask_loss = (scene.resist_top + 0.5) - m_top

    metrics = {
        "etch_depth": depth * vox,
        "top_width": top_w * vox,
        "neck_width": neck * vox,
        "bottom_width": bottom * vox,
        "bowing": bowing * vox,
        "mask_loss": mask_loss * vox,
    }
    return metrics, neck_depth


def profile_metrics_batch(states: Any, scene: Scene) -> dict[str, np.ndarray]:
    """Profile metrics of a sequence of states (see the module docstring for the definitions), a number at
    every step; users are shown ``measured_profile_metrics``.

    Args:
        states: (T, 2, D, H, W) normalized SDF states (numpy or CPU torch).
        scene: the scene the states belong to.
    Returns:
        {name: (T,) float64 in nm} for the names in ``METRIC_NAMES``.
    """
    return _measure(states, scene)[0]


def measured_profile_metrics(states: Any, scene: Scene) -> dict[str, np.ndarray]:
    """The profile metrics as measurements: ``profile_metrics_batch``'s values, NaN at the steps where a
    metric is undefined, plus ``neck_depth`` (module docstring).

    Args:
        states: (T, 2, D, H, W) normalized SDF states (numpy or CPU torch), or their quadrant.
        scene: the scene the states belong to.
    Returns:
        {name: (T,) float64 in nm, NaN where undefined} for the names in ``METRIC_NAMES`` and
        ``neck_depth``.
    """
    metrics, neck_depth = _measure(states, scene)
    out = dict(metrics, neck_depth=neck_depth * scene.voxel_nm)
    depth = metrics["etch_depth"] / scene.voxel_nm  # (T,) voxels
    sidewall = depth - np.maximum(BOTTOM_FRACTION * depth, BOTTOM_MIN_VOX)  # deepest sidewall (voxels down)
    ref = 0.5 + BOW_SKIP_ROWS  # depth of the first reference row (the top Si row's centre: 0.5)
    for name, row in (("top_width", 0.5), ("bottom_width", 0.5), ("neck_width", ref), ("bowing", ref),
                      ("neck_depth", ref)):  # fmt: skip
        out[name] = np.where(sidewall >= row, out[name], np.nan)
    return out


def profile_metrics(state: Any, scene: Scene) -> dict[str, float]:
    """Profile metrics of one (2, D, H, W) normalized SDF state, in nm (see the module docstring)."""
    if hasattr(state, "detach"):
        state = state.detach().cpu().numpy()
    s = np.asarray(state)
    if s.shape != scene.state_shape:
        raise ValueError(f"state shape {s.shape} != scene {scene.name!r} state shape {scene.state_shape}")
    return {k: float(v[0]) for k, v in profile_metrics_batch(s[None], scene).items()}
