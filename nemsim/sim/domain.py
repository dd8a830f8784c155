"""Multi-species voxel state and the scenes' initial geometry ([supp_simulator], "Physical Domain").

A ``Domain`` holds, for every native voxel (x, y, z), the integer amounts of the five surface species in
``TARGETS`` order (Si, SiCl, SiCl2, SiCl3, Resist) and the derived fill fraction

    fill = (Si + SiCl + SiCl2 + SiCl3) / capacity + Resist / resist_capacity   in [0, 1]

(vacuum = 0). Arrays are indexed [x, y, z(, species)] with z growing upward; particles enter at z = nz.

Initial geometry (every scene): Si fills 0 <= z < si_top; resist fills si_top <= z < resist_top except the
opening, the layers above are empty. The opening is the scene's feature (``scene.kind``,
``nemsim.geometry.feature``): a centred cylinder of radius ``opening_radius_vox`` (hole) or the slot
|x - cx| < ``opening_radius_vox`` along all y (trench). Choice where the paper is silent: voxels cut by the
opening's wall get the resist amount of their covered area fraction (estimated on a 16 x 16 sub-grid), so
the initial opening is sub-voxel accurate instead of a staircase.

Quarter domain (``SimConfig.domain`` = "quarter", ``config`` module docstring): ``lower_quadrant`` is the
voxel state of columns [0, nx/2) x [0, ny/2), the box the particles fly in between mirror walls, and
``unfold_quadrant`` rebuilds a full (nx, ny, ...) field from a quadrant field by the two mirrors through
the opening's axis: full[i] = q[i] for i < nx/2 and q[nx - 1 - i] beyond (likewise in y), exactly symmetric.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nemsim.rules.vocab import TARGETS
from nemsim.scenes import Scene

N_TARGETS = len(TARGETS)
SI_CLASS = tuple(i for i, t in enumerate(TARGETS) if t != "Resist")  # Si, SiCl, SiCl2, SiCl3
RESIST = TARGETS.index("Resist")
SI = TARGETS.index("Si")


@dataclass
class Domain:
    """Mutable voxel state of one trajectory.

    Attributes:
      mat: (nx, ny, nz, 5) int32 species amounts, TARGETS order.
      fill: (nx, ny, nz) float64 fill fraction (see module docstring); > 0 means solid for transport.
      capacity: Si-class units in a full voxel. resist_capacity: resist units in a full voxel.
    """

    mat: np.ndarray
    fill: np.ndarray
    capacity: int
    resist_capacity: int

    def copy(self) -> Domain:
        return Domain(self.mat.copy(), self.fill.copy(), self.capacity, self.resist_capacity)

    def totals(self) -> np.ndarray:
        """(5,) int64 total amount of each species."""
        return self.mat.reshape(-1, N_TARGETS).sum(axis=0, dtype=np.int64)

    def fractions(self) -> tuple[np.ndarray, np.ndarray]:
        """(mask, si) fill fractions, each (nx, ny, nz) float32 in [0, 1]; Si includes SiCl_x."""
        si = self.mat[..., list(SI_CLASS)].sum(axis=-1, dtype=np.float64) / self.capacity
        mask = self.mat[..., RESIST].astype(np.float64) / self.resist_capacity
        return mask.astype(np.float32), si.astype(np.float32)


def compute_fill(mat: np.ndarray, capacity: int, resist_capacity: int) -> np.ndarray:
    """(nx, ny, nz) float64 fill fraction from species amounts (module docstring)."""
    si = mat[..., list(SI_CLASS)].sum(axis=-1, dtype=np.float64)
    return si / capacity + mat[..., RESIST] / float(resist_capacity)


def opening_coverage(scene: Scene, sub: int = 16) -> np.ndarray:
    """(nx, ny) float64 fraction of each column's area lying outside the opening (the hole's cylinder or
    the trench's slot, module docstring)."""
    cx, cy = scene.opening_centre  # voxel-centre coordinates: voxel i spans [i - 0.5, i + 0.5]
    offs = (np.arange(sub) + 0.5) / sub - 0.5  # (sub,) sub-sample offsets inside a voxel
    xs = (np.arange(scene.nx)[:, None] + offs[None, :]).reshape(-1)  # (nx*sub,)
    ys = (np.arange(scene.ny)[:, None] + offs[None, :]).reshape(-1)
    if scene.kind == "trench":
        outside = np.broadcast_to(np.abs(xs[:, None] - cx) >= scene.opening_radius_vox, (len(xs), len(ys)))
    else:
        outside = (xs[:, None] - cx) ** 2 + (ys[None, :] - cy) ** 2 >= scene.opening_radius_vox**2
    return outside.reshape(scene.nx, sub, scene.ny, sub).mean(axis=(1, 3))  # (nx, ny)


def initial_domain(scene: Scene, capacity: int, resist_capacity: int) -> Domain:
    """The deterministic initial geometry of ``scene`` ([supp_simulator]; module docstring)."""
    if capacity < 1 or resist_capacity < 1:
        raise ValueError(f"capacities must be >= 1, got {capacity=}, {resist_capacity=}")
    mat = np.zeros((scene.nx, scene.ny, scene.nz, N_TARGETS), dtype=np.int32)
    mat[:, :, : scene.si_top, SI] = capacity
    resist_col = np.rint(opening_coverage(scene) * resist_capacity).astype(np.int32)  # (nx, ny)
    mat[:, :, scene.si_top : scene.resist_top, RESIST] = resist_col[:, :, None]
    return Domain(mat, compute_fill(mat, capacity, resist_capacity), capacity, resist_capacity)


def lower_quadrant(dom: Domain) -> Domain:
    """The voxel state of columns [0, nx/2) x [0, ny/2) of ``dom`` (a copy; nx, ny even)."""
    nx, ny = dom.fill.shape[:2]
    if nx % 2 or ny % 2:
        raise ValueError(f"the quadrant needs even nx and ny, got {nx} x {ny}")
    hx, hy = nx // 2, ny // 2
    return Domain(dom.mat[:hx, :hy].copy(), dom.fill[:hx, :hy].copy(), dom.capacity, dom.resist_capacity)


def unfold_quadrant(q: np.ndarray) -> np.ndarray:
    """(2 qx, 2 qy, ...) full field from a lower-quadrant field q (qx, qy, ...) (module docstring)."""
    half = np.concatenate([q, q[::-1]], axis=0)
    return np.ascontiguousarray(np.concatenate([half, half[:, ::-1]], axis=1))


def section_slab(dom: Domain, nx: int, ny: int) -> Domain:
    """The voxel state of columns [0, nx) x [0, ny) of ``dom`` (a copy): a trench's cross-section slab
    (``SimConfig.domain`` = "section"; a trench's x0 is the same in every row of y)."""
    return Domain(dom.mat[:nx, :ny].copy(), dom.fill[:nx, :ny].copy(), dom.capacity, dom.resist_capacity)


def unfold_section(q: np.ndarray, nx: int, ny: int) -> np.ndarray:
    """(nx, ny, ...) full field from a cross-section slab's field q (sx, sy, ...): mirrored across the trench
    axis when sx < nx (``unfold_quadrant``'s x mirror), and repeated along y as the unfolded traversal between
    the slab's y mirror walls sees it (rows 0..sy-1, then sy-1..0, and so on)."""
    if q.shape[0] < nx:
        q = np.concatenate([q, q[::-1]], axis=0)
    sy = q.shape[1]
    j = np.arange(ny) % (2 * sy)
    return np.ascontiguousarray(q[:, np.where(j < sy, j, 2 * sy - 1 - j)])


def unfold_domain(dom: Domain) -> Domain:
    """The full-box ``Domain`` of a lower-quadrant one (amounts and fill mirrored, ``unfold_quadrant``)."""
    return Domain(unfold_quadrant(dom.mat), unfold_quadrant(dom.fill), dom.capacity, dom.resist_capacity)
