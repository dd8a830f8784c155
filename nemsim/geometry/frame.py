"""The one frame of reference of NEMSim's outputs: meshes, exported grids, metrics and the explorer's views.

x, y: nm from the hole axis (the opening's centre line); z: nm from the initial Si top, positive up
(towards the plasma), so the depth below the initial Si top, the unit of the profile metrics and of the 2-D
views, is -z. The frame is right-handed with z up, so meshes keep their outward winding and open upright in
mesh viewers.

Grid. A native voxel (i, j, k) spans [i, i + 1) * voxel_nm from the box corner; a state's padded index is
native + 1 (``nemsim.scenes``). The box corner therefore sits at (-nx / 2, -ny / 2, -si_top) * voxel_nm.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from nemsim.scenes import Scene

FRAME = (
    "x, y: nm from the hole axis; z: nm above the initial Si top (up, towards the plasma; "
    "depth below the initial Si top = -z)"
)
FRAME_SHORT = "nm, x y from hole axis, z up from initial Si top"  # for 80-byte headers (binary STL)


def box_corner_nm(scene: Scene) -> np.ndarray:
    """(3,) position of the native box's corner (x, y, z) = (0, 0, 0) voxel edge, nm in the frame."""
    return np.array([-scene.nx / 2.0, -scene.ny / 2.0, -float(scene.si_top)]) * scene.voxel_nm


def grid_axes_nm(scene: Scene) -> dict[str, np.ndarray]:
    """Voxel-centre coordinates of a padded state's axes in the frame, nm.

    Returns:
        ``{"x": (W,), "y": (H,), "z": (D,)}``: index p of that axis -> (p - 0.5) * voxel_nm + corner.
    """
    corner = box_corner_nm(scene)
    d, h, w = scene.field_shape
    return {
        name: (np.arange(n) - 0.5) * scene.voxel_nm + corner[a]
        for a, (name, n) in enumerate((("x", w), ("y", h), ("z", d)))
    }


def frame_to_index(points_nm: np.ndarray, scene: Scene) -> np.ndarray:
    """Padded (z, y, x) fractional voxel index of points (N, 3) given as (x, y, z) nm in the frame.

    Returns:
        (N, 3) indices into a padded (D, H, W) field (voxel centres at integers).
    """
    xyz = (np.asarray(points_nm, dtype=np.float64) - box_corner_nm(scene)) / scene.voxel_nm + 0.5
    return xyz[:, ::-1]  # (N, 3) (x, y, z) -> (z, y, x)
