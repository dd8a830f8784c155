"""The decoder's last step at inference, fused: packed residuals -> the k predicted states, written in place.

``NEMSim.predict`` turns the decoder's packed output r (B, 8·2k, d, h, w) into states in several full-size
passes: the voxel shuffle (``depth_to_space``, a strided copy), the crop of the padding, the flux gate's
multiply, x_t + r, the clamp onto [-1, 1], and ``rollout``'s copy into its trajectory buffer. Each pass reads
and writes all k states (k·2·D·H·W floats: 59 MB per call for k = 10 on ``paper``), so on large grids they,
not the convolutions, set a rollout's time. ``write_states`` does all of them in one pass, reading r and x_t
once and writing each state once, straight into the caller's buffer. It computes the same float32
operations in the same order as ``predict`` (gate·r, then + x_t, then clamp), so the states are identical
(tests/model/test_unpack.py). The OpenVINO runtime exports the network up to r and calls it too.

Used by ``NEMSim.predict_into`` (``rollout``'s fast path) only outside autograd and autocast; training and
bf16 inference keep the PyTorch path.
"""

from __future__ import annotations

import numba
import numpy as np
import torch


@numba.njit(cache=True, nogil=True)
def _write_states(x: np.ndarray, r: np.ndarray, gate: np.ndarray, clamp: bool, out: np.ndarray) -> None:
    """out[b, j, c, z, y, w] = clamp(x[b, c, z, y, w] + gate[b]·r[b, (2j+c)·8 + 4(z%2) + 2(y%2) + w%2,
    z//2, y//2, w//2]) for j < out.shape[1]: x (B, 2, D, H, W), r (B, 16k, d, h, w) with 2d >= D, ..."""
    B, n = out.shape[0], out.shape[1]
    D, H, W = x.shape[2], x.shape[3], x.shape[4]
    for b in range(B):
        g = gate[b]
        for c in range(2):
            for z in range(D):
                zi = z >> 1
                for y in range(H):
                    yi = y >> 1
                    row = 4 * (z & 1) + 2 * (y & 1)
                    for j in range(n):  # x's row stays in cache across the k states
                        ch = (2 * j + c) * 8 + row
                        for w in range(W):
                            v = x[b, c, z, y, w] + g * r[b, ch + (w & 1), zi, yi, w >> 1]
                            if clamp:
                                v = min(max(v, np.float32(-1.0)), np.float32(1.0))
                            out[b, j, c, z, y, w] = v


def write_states(x: torch.Tensor, r: torch.Tensor, gate: torch.Tensor | None, clamp: bool,
                 out: torch.Tensor) -> torch.Tensor:
    """Write the first n = out.shape[1] predicted states into out (B, n, 2, D, H, W), float32 CPU (any
    strides), from x (B, 2, D, H, W) and the decoder's packed residuals r (B, 16k, d, h, w); gate (B,) or
    None."""
    if any(t.dtype != torch.float32 for t in (x, r, out)):
        raise ValueError("write_states needs float32 tensors")
    g = torch.ones(x.shape[0]) if gate is None else gate.detach().float().reshape(-1)
    _write_states(x.detach().numpy(), r.detach().numpy(), g.numpy(), bool(clamp), out.detach().numpy())
    return out
