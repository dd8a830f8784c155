"""Differentiable profile metrics (torch), the gradient-friendly twins of ``nemsim.geometry.profile``.

Inverse design (``nemsim.analysis.inverse``) follows gradients of profile metrics through the surrogate's
rollout. The exact metrics locate zero crossings with argmax/first-crossing scans, whose gradient is zero
almost everywhere. Here every length is a sum of per-voxel "vacuum fractions"

    f(phi) = clamp(phi + 1/2, 0, 1),   phi = SDF in voxels (normalized SDF * d_max / voxel size),

which, for a signed distance with unit slope, is the exact length of vacuum a voxel of edge 1 holds along
the scan direction: summed over a column or a line it gives the same depth or width as the exact
first-crossing definition (module docstring of ``profile``) whenever the scan meets one vacuum interval,
and it is piecewise linear in the field, so gradients flow through the voxels next to the surface.

Definitions (same coordinates as ``profile``; index = native + 1; all results in nm):
  * ``etch_depth``: sum of f over the Si rows of the Si channel on the hole axis (native rows 0..si_top-1).
  * width of a row: mean over the x and y lines through the axis of the summed f (the vacuum length); a
    trench: the x line of the state's mean over y (as ``profile``).
  * ``top_width``: the width of the top Si row.
  * ``bottom_width``: the width of the Si plane interpolated (tent weights, differentiable in the height)
    at h_b = max(0.1 * depth, 1 voxel) above the floor, the floor being si_top + 1/2 - depth.
  * ``mask_loss``: mean over the planar field columns (``profile._field_columns_mask``) of the summed f of
    the mask channel over the mask rows, minus the vacuum rows above the initial resist top.
  * ``bowing``: the exact definition (excess of a row's width over the narrowest row above it, from
    ``BOW_SKIP_ROWS`` below the top Si row, rows inside the hole) on the soft widths; max and running min
    are sub-differentiable.

The soft and exact metrics agree to within a fraction of a voxel on the data (what ``nemsim inverse``
reports is always the exact one: the soft metrics only steer the search).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from nemsim.geometry.profile import BOTTOM_FRACTION, BOTTOM_MIN_VOX, BOW_SKIP_ROWS, _field_columns_mask

if TYPE_CHECKING:
    from nemsim.scenes import Scene

SOFT_METRICS = ("etch_depth", "top_width", "bottom_width", "bowing", "mask_loss")


def _vacuum(field: torch.Tensor, scene: Scene) -> torch.Tensor:
    """Vacuum fraction f(phi) of normalized SDF samples (any shape)."""
    return (field * scene.d_max_vox + 0.5).clamp(0.0, 1.0)


def _at(field: torch.Tensor, dim: int, at: float) -> torch.Tensor:
    """field at a (half-)integer index along ``dim``, linear interpolation (as ``profile._interp_at``)."""
    lo = int(at // 1)
    w = at - lo
    a = field.select(dim, lo)
    return a if w < 1e-9 else (1.0 - w) * a + w * field.select(dim, lo + 1)


def _plane_width(si: torch.Tensor, scene: Scene) -> torch.Tensor:
    """Width (voxels) of Si planes (..., H, W): mean vacuum length of the x and y lines through the axis (a
    trench: of the x line only)."""
    ax_x = scene.opening_centre[0] + 1.0
    ax_y = scene.opening_centre[1] + 1.0
    x_line = _at(si, si.dim() - 2, ax_y)[..., 1:-1]  # (..., nx) native samples
    if scene.kind == "trench":
        return _vacuum(x_line, scene).sum(-1)
    y_line = _at(si, si.dim() - 1, ax_x)[..., 1:-1]  # (..., ny)
    return 0.5 * (_vacuum(x_line, scene).sum(-1) + _vacuum(y_line, scene).sum(-1))


def soft_profile_metrics(states: torch.Tensor, scene: Scene) -> dict[str, torch.Tensor]:
    """Differentiable profile metrics of normalized SDF states.

    Args:
        states: (B, 2, D, H, W) normalized SDF (channel 0 mask, 1 Si).
        scene: the scene of the states.
    Returns:
        {name: (B,) nm} for the names in ``SOFT_METRICS``.
    """
    if states.dim() != 5 or tuple(states.shape[1:]) != scene.state_shape:
        raise ValueError(f"states shape {tuple(states.shape)}; expected (B, *{scene.state_shape})")
    vox = scene.voxel_nm
    if scene.kind == "trench":  # the line's mean profile (``profile`` module docstring)
        states = states.mean(dim=3, keepdim=True).expand_as(states)
    mask, si = states[:, 0], states[:, 1]  # (B, D, H, W)
    top = scene.si_top  # index of the top Si row
    ax_x = scene.opening_centre[0] + 1.0
    ax_y = scene.opening_centre[1] + 1.0

    col = _at(_at(si, 3, ax_x), 2, ax_y)  # (B, D) Si on the axis
    depth = _vacuum(col[:, 1 : top + 1], scene).sum(-1)  # (B,) voxels
    widths = _plane_width(si[:, 1 : top + 1], scene)  # (B, top) rows index 1..top
    top_w = widths[:, -1]

    floor = (top + 0.5) - depth  # (B,) index coordinate of the floor
    z_b = (floor + torch.clamp(BOTTOM_FRACTION * depth, min=BOTTOM_MIN_VOX)).clamp(1.0, float(top))
    rows = torch.arange(1, top + 1, dtype=states.dtype, device=states.device)  # (top,)
    tent = (1.0 - (rows[None, :] - z_b[:, None]).abs()).clamp(min=0.0)  # (B, top) interpolation weights
    plane = torch.einsum("bz,bzhw->bhw", tent, si[:, 1 : top + 1])  # (B, H, W)
    bottom = _plane_width(plane, scene)

    ref = top - 1 - BOW_SKIP_ROWS  # column of the first reference row in widths
    if ref >= 0:
        w_down = widths[:, : ref + 1].flip(1)  # (B, ref + 1) top to bottom
        in_hole = rows[: ref + 1].flip(0)[None, :] > floor.detach()[:, None]  # (B, ref + 1)
        big = torch.finfo(states.dtype).max / 4
        neck = torch.cummin(torch.where(in_hole, w_down, torch.full_like(w_down, big)), dim=1).values
        excess = torch.where(in_hole, w_down - neck, torch.full_like(w_down, -big))
        bowing = excess.max(dim=1).values.clamp(min=0.0)
    else:
        bowing = torch.zeros_like(depth)

    sel = torch.as_tensor(_field_columns_mask(scene), device=states.device)  # (ny, nx)
    m_cols = mask[:, top + 1 : scene.nz + 1, 1:-1, 1:-1][:, :, sel]  # (B, rows, K)
    mask_loss = _vacuum(m_cols, scene).sum(1).mean(-1) - (scene.nz - scene.resist_top)

    return {
        "etch_depth": depth * vox,
        "top_width": top_w * vox,
        "bottom_width": bottom * vox,
        "bowing": bowing * vox,
        "mask_loss": mask_loss * vox,
    }
