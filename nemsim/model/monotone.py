"""Monotone projection of a rollout: etching only removes material (``NEMSimConfig.monotone_eps``).

Every process of the simulator removes material (redeposition, the only addition, is small), so the signed
distance of each material (negative inside; channel 0 mask, 1 Si; SDF / d_max clipped to [-1, 1]) is
non-decreasing in time at every voxel. A surrogate rolled out past its training need not keep this (a hole
can refill, a mask grow), so the rollout carries the running maximum M_t of its own projected states,
M_0 = x_0, and replaces each predicted state by

  x̂_t <- max(x̂_t, M_{t-1} - eps_c),   M_t = max(M_{t-1}, x̂_t)         (per voxel, eps_c per channel)

the Euclidean projection onto {x : x >= M_{t-1} - eps}: no surface moves back by more than about
eps * d_max nm at any horizon; states that already satisfy it are unchanged.

Why eps > 0: the simulator's own states are only nearly monotone (the SDF is rebuilt from a voxel occupancy
field and smoothed), and eps = 0 turns a prediction's zero-mean noise into an upward ratchet.

The hole axis (``axis_eps``, ``NEMSimConfig.monotone_axis_eps``): the etch depth is read on the hole axis,
interpolated between the (up to) 2 x 2 voxel columns around it (``nemsim.geometry.profile``); those columns
get their own slack. With axis_eps = 0 each of them is non-decreasing, so is their convex combination, and
the first vacuum->Si crossing on that line can only move down: the depth never decreases, by construction.
Elsewhere a tight slack would turn the sidewalls' sub-voxel noise into a width bias. The axis is the
domain's centre line (``Scene.opening_centre``), found from the state's shape alone.

``MONOTONE_EPS`` (mask, Si): the Si value is the 99.9th percentile of the data's fall below its running
maximum over the ``small`` control-id training cases (``nemsim bench monotone-eps``,
benchmarks/small/monotone_eps.json); the mask value is the smaller of that and the simulator's seed-to-seed
mask-loss difference / d_max. A property of the simulator and the representation, not of a checkpoint:
older checkpoints load it too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np
import torch

from nemsim.symmetry import model_fold

# (mask, Si) in normalized SDF units: how they were chosen, module docstring
MONOTONE_EPS: tuple[float, float] = (0.005, 0.034)
# Si slack on the hole-axis columns (the etch depth's readout): 0 makes the depth non-decreasing exactly
MONOTONE_AXIS_EPS: float = 0.0
SI_CHANNEL = 1


def axis_columns(h: int, w: int, full_size: int | None = None,
                 all_rows: bool = False) -> tuple[list[int], list[int]]:
    """(y indices, x indices) of the padded voxel columns the hole-axis readout interpolates between, for a
    state of padded size (H, W) = (h, w): the axis sits at index (n - 1) / 2 of an axis of padded size n
    (native centre (n_native - 1) / 2, plus the one-voxel pad), so one column when n is odd, two when even.
    ``full_size``: the state is the lower quadrant (``nemsim.symmetry.fold``) of a field of that lateral
    size; the columns are those of the full field that lie in the quadrant. ``all_rows``: a trench's axis
    is a line along y, so every row's axis columns (a cross-section's, or a full trench field's)."""
    def cols(n: int, m: int) -> list[int]:
        a = (n - 1) / 2.0
        return [i for i in sorted({math.floor(a), math.ceil(a)}) if i < m]

    return (list(range(h)) if all_rows else cols(full_size or h, h)), cols(full_size or w, w)


def eps_field(shape: Sequence[int], eps: Sequence[float], axis_eps: float | None,
              dtype: torch.dtype = torch.float32, device: torch.device | str | None = None,
              full_size: int | None = None, all_rows: bool = False) -> torch.Tensor:
    """The per-voxel slack of the projection, (1, C, 1, H, W) (broadcast over batch and depth): ``eps`` per
    channel, and ``axis_eps`` on the Si channel's hole-axis columns (None: no separate axis slack).

    shape: a state's (..., C, D, H, W) shape; ``full_size``, ``all_rows``: as in ``axis_columns``."""
    c, h, w = int(shape[-4]), int(shape[-2]), int(shape[-1])
    if len(eps) != c or any(not float(e) >= 0.0 for e in eps):
        raise ValueError(f"eps must be {c} values >= 0 (one per channel), got {tuple(eps)}")
    field = torch.tensor([float(e) for e in eps], dtype=dtype, device=device).view(1, c, 1, 1, 1)
    field = field.expand(1, c, 1, h, w).clone()  # (1, C, 1, H, W)
    if axis_eps is not None:
        if not float(axis_eps) >= 0.0 or c <= SI_CHANNEL:
            raise ValueError(f"axis_eps must be >= 0 on a state with a Si channel, got {axis_eps!r}")
        ys, xs = axis_columns(h, w, full_size, all_rows)
        for y in ys:
            field[0, SI_CHANNEL, 0, y, xs] = float(axis_eps)
    return field


class MonotoneProjection:
    """The running maximum of a rollout and the projection onto x >= M - eps (module docstring).

    Args:
        x0: (B, 2, D, H, W) the initial states (the first running maximum; not modified).
        eps: per-channel slack (C values, C = x0.shape[1]).
        axis_eps: the Si slack on the hole-axis columns (``eps_field``); None: ``eps`` there too.
        full_size: x0 is the lower quadrant (or a cross-section) of fields of this lateral size.
        all_rows: the axis columns of every row (a trench's axis line; ``axis_columns``).
    """

    def __init__(self, x0: torch.Tensor, eps: Sequence[float], axis_eps: float | None = None,
                 full_size: int | None = None, all_rows: bool = False) -> None:
        self.eps = eps_field(x0.shape, eps, axis_eps, x0.dtype, x0.device, full_size,
                             all_rows)  # (1, 2, 1, H, W)
        self.running_max = x0.clone()  # (B, 2, D, H, W)
        self._floor: torch.Tensor | None = None  # (B, 2, D, H, W) scratch of project_

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """The projection of the next state x (B, 2, D, H, W); updates the running maximum."""
        x = torch.maximum(x, self.running_max - self.eps)  # (B, 2, D, H, W)
        torch.maximum(self.running_max, x, out=self.running_max)
        return x

    def project_(self, x: torch.Tensor) -> torch.Tensor:
        """``__call__`` in place: x (B, 2, D, H, W) is overwritten by its projection (the same values, no
        allocation per state: the rollout projects its trajectory buffer)."""
        if self._floor is None:
            self._floor = torch.empty_like(self.running_max)
        torch.sub(self.running_max, self.eps, out=self._floor)  # (B, 2, D, H, W) M - eps
        torch.maximum(x, self._floor, out=x)
        torch.maximum(self.running_max, x, out=self.running_max)
        return x


    def project_chunk_(self, states: torch.Tensor) -> torch.Tensor:
        """``project_`` of the n consecutive states (B, n, 2, D, H, W) of one call, in order, in place. On a
        GPU in a fixed number of kernels (the running maximum after state j is the maximum of the previous
        one and the unprojected x_j, a cumulative maximum; the same values exactly), so a rollout's projection
        costs a few launches per call instead of three per state; on the CPU in one compiled pass over the
        states, the same float32 operations voxel by voxel (M - eps, then the two maxima))."""
        if states.device.type == "cpu":
            if states.dtype == torch.float32 and not states.requires_grad and self.eps.dtype == torch.float32:
                eps = self.eps[0, :, 0].numpy()  # (C, H, W)
                _project_chunk_cpu(states.detach().numpy(), self.running_max.numpy(), eps)
                return states
            for j in range(states.shape[1]):
                self.project_(states[:, j])
            return states
        if states.shape[1] == 1:
            self.project_(states[:, 0])
            return states
        return self._project_chunk_vectorized_(states)

    def _project_chunk_vectorized_(self, states: torch.Tensor) -> torch.Tensor:
        """``project_chunk_``'s GPU form on any device (tests compare it with the state-by-state form)."""
        M = self.running_max  # (B, 2, D, H, W)
        cm = torch.cummax(states, dim=1).values  # (B, n, ...) running max of the unprojected states
        prev = torch.cat([M[:, None], torch.maximum(M[:, None], cm[:, :-1])], dim=1)  # M_{j-1}
        torch.maximum(states, prev.sub_(self.eps[:, None]), out=states)
        torch.maximum(M, cm[:, -1], out=M)
        return states


@numba.njit(cache=True, nogil=True)
def _project_chunk_cpu(states: np.ndarray, m: np.ndarray, eps: np.ndarray) -> None:
    """states (B, n, C, D, H, W) projected in order onto x >= M - eps, M (B, C, D, H, W) updated, in place;
    eps (C, H, W)."""
    B, n, C, D = states.shape[:4]
    for b in range(B):
        for j in range(n):
            for c in range(C):
                for z in range(D):
                    project_plane_(states[b, j, c, z], m[b, c, z], eps[c])


@numba.njit(inline="always")
def project_plane_(plane: np.ndarray, m: np.ndarray, eps: np.ndarray) -> None:
    """One (H, W) plane of a state projected onto >= m - eps and its running maximum m updated, in place
    (the projection's arithmetic, shared with the fused writer ``nemsim.model.unpack``)."""
    for y in range(plane.shape[0]):
        for x in range(plane.shape[1]):
            mv = m[y, x]
            v = nan_maximum(plane[y, x], mv - eps[y, x])
            plane[y, x] = v
            m[y, x] = nan_maximum(mv, v)


@numba.njit(inline="always")
def nan_maximum(a: float, b: float) -> float:
    """``torch.maximum`` of two scalars: NaN when either is NaN (a non-finite prediction stays visible)."""
    return a if (a >= b or a != a) else b


def project(x: torch.Tensor, running_max: torch.Tensor,
            eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The same projection without in-place updates, so gradients flow through it (inverse design):
    (projected x, new running maximum), all (B, 2, D, H, W); eps (1, 2, 1, H, W) from ``eps_field``."""
    x = torch.maximum(x, running_max - eps)
    return x, torch.maximum(running_max, x)


def monotone_eps_of(model: object, monotone: bool | None) -> tuple[float, ...] | None:
    """The eps a rollout of ``model`` projects with, or None for no projection.

    ``monotone`` None follows the model (``model.config.monotone_eps``; models without the key, such as
    the baselines, are not projected); False is off; True is on with the model's eps, or ``MONOTONE_EPS``
    for a model that has none.
    """
    if monotone is False:
        return None
    eps = getattr(getattr(model, "config", None), "monotone_eps", None)
    if eps is None and monotone:
        eps = MONOTONE_EPS
    return None if eps is None else tuple(float(e) for e in eps)


def axis_eps_of(model: object) -> float | None:
    """The hole-axis Si slack of ``model``'s rollouts: ``model.config.monotone_axis_eps`` (None: the Si
    ``eps`` there too), ``MONOTONE_AXIS_EPS`` for a model whose config has no such key."""
    value = getattr(getattr(model, "config", None), "monotone_axis_eps", MONOTONE_AXIS_EPS)
    return None if value is None else float(value)


def projection_of(model: object, x0: torch.Tensor, monotone: bool | None) -> MonotoneProjection | None:
    """The monotone projection of a rollout of ``model`` from x0 (B, 2, D, H, W), or None (``monotone``
    as in ``monotone_eps_of``)."""
    eps = monotone_eps_of(model, monotone)
    f = model_fold(model)  # x0 may be the folded part of a quarter- or section-domain model's field
    if eps is None:
        return None
    return MonotoneProjection(x0, eps, axis_eps_of(model), f.n if f and not f.is_full(x0) else None,
                              f is not None and f.kind == "section")


def running_max_drop(states: np.ndarray) -> np.ndarray:
    """Per voxel and step, how far each state lies below its running maximum: (T+1, C, D, H, W) <= 0.

    states: (T+1, C, D, H, W) one trajectory.
    """
    return states - np.maximum.accumulate(states, axis=0)


def measure_eps(path: str, rows: Sequence[int], quantiles: Sequence[float] = (0.99, 0.999, 0.9999, 1.0)
                ) -> dict[str, object]:
    """Quantiles of the fall below the running maximum, per channel, over the trajectories in ``rows`` of a
    design file (``states`` rows); only voxels whose value changes at some step count (a static voxel never
    falls). Returns {"file", "cases", "mask": {"q0.999": ...}, "si": {...}, "si_axis": {...}} in normalized
    SDF units; "si_axis" is the Si channel on the hole-axis columns alone (``axis_columns``)."""
    import h5py

    falls: list[list[np.ndarray]] = [[], [], []]  # mask, Si, Si on the hole-axis columns
    with h5py.File(path, "r") as f:
        for row in rows:
            states = np.asarray(f["states"][int(row)], dtype=np.float32)  # (T+1, 2, D, H, W)
            drop = -running_max_drop(states)  # >= 0
            moving = (states.max(axis=0) > states.min(axis=0))  # (2, D, H, W)
            for c in range(states.shape[1]):
                falls[c].append(drop[:, c][:, moving[c]].ravel())
            on_axis = np.zeros(moving.shape[1:], dtype=bool)  # (D, H, W)
            ys, xs = axis_columns(*moving.shape[2:])
            on_axis[:, ys[0] : ys[-1] + 1, xs[0] : xs[-1] + 1] = True
            falls[2].append(drop[:, SI_CHANNEL][:, moving[SI_CHANNEL] & on_axis].ravel())
    out: dict[str, object] = {"file": str(path), "cases": len(rows)}
    for c, name in enumerate(("mask", "si", "si_axis")):
        v = np.concatenate(falls[c])
        out[name] = {f"q{q:g}": float(np.quantile(v, q)) for q in quantiles} if v.size else {}
    return out
