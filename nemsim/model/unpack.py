"""The decoder's last step at inference, fused: packed residuals -> the k predicted states, written in place.

``NEMSim.predict`` turns the decoder's packed output r (B, 8·2k, d, h, w) into states in several full-size
passes: the voxel shuffle (``depth_to_space``, a strided copy), the crop of the padding, the flux gate's
multiply, x_t + r, the clamp onto [-1, 1], and ``rollout``'s copy into its trajectory buffer. Each pass reads
and writes all k states (k·2·D·H·W floats: 59 MB per call for k = 10 on ``paper``), so on large grids they,
not the convolutions, set a rollout's time. ``write_states`` does all of them in one pass, reading r and x_t
once and writing each state once, straight into the caller's buffer. It computes the same float32
operations in the same order as ``predict`` (gate·r, then + x_t, then clamp), so the states are identical
(tests/model/test_unpack.py). The OpenVINO runtime exports the network up to r and calls it too.

The rollout's own passes over a call's states follow in the same pass (``Finish``): a quarter-domain
model's diagonal mean (``nemsim.symmetry.symmetrize_diagonal_``) and the monotone projection
(``nemsim.model.monotone``), each plane of a state finished while it is still in the cache. Three compiled
passes over every state took a quarter of a 100-step `small` rollout; the fused one computes the same
float32 operations in the same order, so the states are identical (tests/model/test_unpack.py).

Used by ``NEMSim.predict_into`` (``rollout``'s fast path) only outside autograd and autocast; training and
bf16 inference keep the PyTorch path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numba
import numpy as np
import torch

from nemsim.model.monotone import project_plane_
from nemsim.symmetry import rows_mean_, symmetrize_diagonal_, symmetrize_plane_

if TYPE_CHECKING:
    from nemsim.model.monotone import MonotoneProjection


@dataclass(frozen=True)
class Finish:
    """What a rollout does to a call's states once they are written (module docstring): ``diagonal``, the
    mean of each (c, c) plane with its transpose (a quarter-domain model's diagonal mirror), or ``rows``,
    each plane's rows replaced by their mean (a cross-section's), then ``projection``'s monotone
    projection, state after state (None: none)."""

    diagonal: bool = False
    projection: MonotoneProjection | None = None
    rows: bool = False

    def apply_(self, states: torch.Tensor) -> torch.Tensor:
        """The finish of states (B, n, 2, D, H, W) in place, pass after pass (paths that do not fuse it)."""
        if self.diagonal:
            symmetrize_diagonal_(states)
        if self.rows:
            rows_mean_(states)
        if self.projection is not None:
            self.projection.project_chunk_(states)
        return states


NO_FINISH = Finish()


@numba.njit(cache=True, nogil=True)
def _write_states(x: np.ndarray, r: np.ndarray, gate: np.ndarray, clamp: bool, diagonal: bool, rows: bool,
                  m: np.ndarray, eps: np.ndarray, out: np.ndarray) -> None:
    """out[b, j, c, z, y, w] = clamp(x[b, c, z, y, w] + gate[b]·r[b, (2j+c)·8 + 4(z%2) + 2(y%2) + w%2,
    z//2, y//2, w//2]) for j < out.shape[1]: x (B, 2, D, H, W), r (B, 16k, d, h, w) with 2d >= D, ...
    Then, plane by plane (``Finish``): with ``diagonal`` each (y, w), (w, y) pair replaced by its mean (H ==
    W), with ``rows`` each plane's rows by their mean; with m (B, 2, D, H, W), the running maximum (else
    size 0), the projection onto >= m - eps[c, y, w], m updated, state after state."""
    B, n = out.shape[0], out.shape[1]
    D, H, W = x.shape[2], x.shape[3], x.shape[4]
    project = m.shape[0] > 0
    for b in range(B):
        g = gate[b]
        for j in range(n):
            for c in range(2):
                ch = (2 * j + c) * 8
                for z in range(D):
                    zi = z >> 1
                    plane = out[b, j, c, z]
                    for y in range(H):
                        yi = y >> 1
                        row = ch + 4 * (z & 1) + 2 * (y & 1)
                        for w in range(W):
                            v = x[b, c, z, y, w] + g * r[b, row + (w & 1), zi, yi, w >> 1]
                            if clamp:
                                v = min(max(v, np.float32(-1.0)), np.float32(1.0))
                            plane[y, w] = v
                    if diagonal:
                        symmetrize_plane_(plane)
                    if rows:
                        _rows_mean_plane(plane)
                    if project:
                        project_plane_(plane, m[b, c, z], eps[c])


@numba.njit(inline="always")
def _rows_mean_plane(a: np.ndarray) -> None:
    """Every row of one (H, W) plane replaced by the mean of its H rows, in place (float32 sums)."""
    h, w = a.shape
    inv = np.float32(1.0) / np.float32(h)
    for j in range(w):
        s = np.float32(0.0)
        for i in range(h):
            s += a[i, j]
        v = s * inv
        for i in range(h):
            a[i, j] = v


def write_states(x: torch.Tensor, r: torch.Tensor, gate: torch.Tensor | None, clamp: bool,
                 out: torch.Tensor, finish: Finish = NO_FINISH) -> torch.Tensor:
    """Write the first n = out.shape[1] predicted states into out (B, n, 2, D, H, W), float32 CPU (any
    strides), from x (B, 2, D, H, W) and the decoder's packed residuals r (B, 16k, d, h, w); gate (B,) or
    None; ``finish`` done in the same pass."""
    if any(t.dtype != torch.float32 for t in (x, r, out)):
        raise ValueError("write_states needs float32 tensors")
    g = torch.ones(x.shape[0]) if gate is None else gate.detach().float().reshape(-1)
    if finish.diagonal and x.shape[-1] != x.shape[-2]:
        raise ValueError(f"the diagonal mean needs square planes, got {tuple(x.shape[-2:])}")
    proj = finish.projection
    if proj is None:
        m, eps = np.empty((0, 2, 1, 1, 1), np.float32), np.empty((2, 1, 1), np.float32)
    else:  # the running maximum of x's rollout: float32 on the CPU like x
        m, eps = proj.running_max.numpy(), proj.eps[0, :, 0].contiguous().numpy()
    _write_states(x.detach().numpy(), r.detach().numpy(), g.numpy(), bool(clamp), finish.diagonal,
                  finish.rows, m, eps, out.detach().numpy())
    return out
