"""Monotone projection of a rollout: etching only removes material (``NEMSimConfig.monotone_eps``).

Every process of the simulator removes material (ion sputtering, chemical etching, product desorption;
redeposition is the only addition and it is small), so the exact signed distance of each material
(negative inside it; channel 0 = mask, channel 1 = Si; normalized by d_max and clipped to [-1, 1]) is
non-decreasing in time at every voxel. A surrogate rolled out past what it was trained on need not keep
this: a hole's SDF can relax back toward the surface, a mask can grow. The rollout therefore carries the
running maximum M_t of its own (projected) states, M_0 = x_0, and replaces each predicted state by

  x̂_t <- max(x̂_t, M_{t-1} - eps_c),   M_t = max(M_{t-1}, x̂_t)         (per voxel, eps_c per channel)

the Euclidean projection onto {x : x >= M_{t-1} - eps}. So no voxel ever falls more than eps below any value
it held earlier, whatever the horizon; states that already satisfy it are returned unchanged.

Why eps > 0: the simulator's own stored states are only nearly monotone (the SDF is reconstructed from a
voxel occupancy field and smoothed: sub-voxel noise), and a projection with eps = 0 turns a prediction's
zero-mean noise into an upward ratchet (it cost accuracy on control-id). What eps buys: since every voxel
stays within eps of its running maximum, no surface can move back by more than about eps * d_max nm, so the
rollout's etch depth and mask loss can never fall by more than that, at any horizon.

How ``MONOTONE_EPS`` (mask, Si) was chosen (figures in ``benchmarks/small/monotone.md``): the Si value is
the 99.9th percentile of the data's fall below the running maximum over the ``small`` design's control-id
training cases (``nemsim bench monotone-eps``); the mask value is the smaller of that percentile and the
simulator's seed-to-seed mask-loss difference / d_max, so mask regrowth stays within the simulator's own
noise. Each was kept only because control-id Avg RMSE did not get worse with it. The value is a property of
the simulator and the representation, not of a checkpoint's weights: every checkpoint whose stored config
lacks the key loads with this default.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

# (mask, Si) in normalized SDF units: see the module docstring for how it was measured
MONOTONE_EPS: tuple[float, float] = (0.005, 0.034)


class MonotoneProjection:
    """The running maximum of a rollout and the projection onto x >= M - eps (module docstring).

    Args:
        x0: (B, 2, D, H, W) the initial states (the first running maximum; not modified).
        eps: per-channel slack (C values, C = x0.shape[1]).
    """

    def __init__(self, x0: torch.Tensor, eps: Sequence[float]) -> None:
        if len(eps) != x0.shape[1] or any(not float(e) >= 0.0 for e in eps):
            raise ValueError(f"eps must be {x0.shape[1]} values >= 0 (one per channel), got {tuple(eps)}")
        self.running_max = x0.clone()  # (B, 2, D, H, W)
        eps_t = torch.tensor([float(e) for e in eps], dtype=x0.dtype, device=x0.device)
        self.eps = eps_t.view(1, -1, 1, 1, 1)  # (1, 2, 1, 1, 1)
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


def project(x: torch.Tensor, running_max: torch.Tensor,
            eps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The same projection without in-place updates, so gradients flow through it (inverse design):
    (projected x, new running maximum), all (B, 2, D, H, W); eps (1, 2, 1, 1, 1)."""
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


def running_max_drop(states: np.ndarray) -> np.ndarray:
    """Per voxel and step, how far each state lies below its running maximum: (T+1, C, D, H, W) <= 0.

    states: (T+1, C, D, H, W) one trajectory.
    """
    return states - np.maximum.accumulate(states, axis=0)


def measure_eps(path: str, rows: Sequence[int], quantiles: Sequence[float] = (0.99, 0.999, 0.9999, 1.0)
                ) -> dict[str, object]:
    """Quantiles of the fall below the running maximum, per channel, over the trajectories in ``rows`` of a
    design file (``states`` rows); only voxels whose value changes at some step count (a static voxel never
    falls). Returns {"file", "cases", "mask": {"q0.999": ...}, "si": {...}} in normalized SDF units."""
    import h5py

    falls: list[list[np.ndarray]] = [[], []]
    with h5py.File(path, "r") as f:
        for row in rows:
            states = np.asarray(f["states"][int(row)], dtype=np.float32)  # (T+1, 2, D, H, W)
            drop = -running_max_drop(states)  # >= 0
            moving = (states.max(axis=0) > states.min(axis=0))  # (2, D, H, W)
            for c in range(states.shape[1]):
                falls[c].append(drop[:, c][:, moving[c]].ravel())
    out: dict[str, object] = {"file": str(path), "cases": len(rows)}
    for c, name in enumerate(("mask", "si")):
        v = np.concatenate(falls[c])
        out[name] = {f"q{q:g}": float(np.quantile(v, q)) for q in quantiles}
    return out
