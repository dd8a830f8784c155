"""Analytic SDF states for the geometry tests (tiny scene)."""

from __future__ import annotations

import numpy as np
import pytest


def hole_state(scene, radius_vox, depth_vox, *, mask_top=None, bow=0.0, bow_depth=None):
    """(2, D, H, W) normalized state: Si slab with a flat-bottom cylindrical hole of ``radius_vox``
    and ``depth_vox`` below the initial Si top, under a resist layer (top at ``mask_top``, native z).
    ``bow`` widens the hole by that many voxels in a band around native z = ``bow_depth``."""
    d, h, w = scene.field_shape
    z = np.arange(d, dtype=np.float64)[:, None, None] - 1.0  # native coordinates
    y = np.arange(h, dtype=np.float64)[None, :, None] - 1.0
    x = np.arange(w, dtype=np.float64)[None, None, :] - 1.0
    cx, cy = scene.opening_centre
    r = np.hypot(x - cx, y - cy)
    s_top = scene.si_top - 0.5
    floor = s_top - depth_vox
    radius = radius_vox + (bow * (np.abs(z - bow_depth) <= 1.0) if bow_depth is not None else 0.0)
    si = np.maximum(z - s_top, np.minimum(radius - r, z - floor))
    m_top = scene.resist_top - 0.5 if mask_top is None else mask_top
    mask = np.maximum(np.maximum(z - m_top, s_top - z), scene.opening_radius_vox - r)
    st = np.stack([np.broadcast_to(mask, (d, h, w)), np.broadcast_to(si, (d, h, w))])
    return np.clip(st / scene.d_max_vox, -1.0, 1.0).astype(np.float32)


@pytest.fixture
def make_hole():
    return hole_state
