"""Field and surface metrics of [supp_protocols] ("Field-Error Metrics", "Final-Surface Chamfer Distance",
"Parameters").

Field errors (eq:supp_case_step_mse, eq:supp_step_rmse, eq:supp_avg_rmse, eq:supp_final_rmse), computed in
the normalized two-channel SDF representation:

    e_{i,t}  = ||x̂_t^(i) - x_t^(i)||² / V            (V = elements of one state tensor)
    RMSE_t   = sqrt(mean_i e_{i,t})                  (mean over cases first, then the square root)
    Avg RMSE = mean_{t=1..H} RMSE_t                  (NOT sqrt of the time-averaged MSE)
    Final    = RMSE_H

Chamfer distance (eq:supp_chamfer_distance), per state and channel:
  1. crop the channel to the scene's inclusive depth range (channel 0 = mask: ``scene.mask_crop``,
     channel 1 = Si: ``scene.si_crop``), all H and W;
  2. marching cubes at level 0 with spacing (1, 1, 1) (voxel units, crop-index coordinates);
  3. 20,000 points sampled with probability proportional to triangle area, uniformly inside the chosen
     triangle; the generator is ``np.random.default_rng([case_id, step, channel])`` - the same seed for the
     predicted and the reference surface (the paper says the seed is determined by trajectory, step and
     channel; it does not say whether the two surfaces use distinct streams - we use one);
  4. if the cropped field has no zero crossing (marching cubes finds no surface, or only zero-area
     triangles), the point set is the centres of all voxels whose |SDF| equals the crop's minimum |SDF|
     (deterministic fallback; with a fully clipped crop that is every voxel centre);
  5. CD = ½ [mean_p min_q ||p - q|| + mean_q min_p ||q - p||], Euclidean, unsquared, via scipy cKDTree;
  6. the state's CD is the mean of the two channel CDs, in voxel units.

Params (eq:supp_params): trainable scalars, shared parameter objects counted once (``nn.Module.parameters``
already de-duplicates shared tensors).

Arrays may be numpy arrays or CPU torch tensors; everything is computed in float64 numpy.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # keep the module import-light; torch and the scene are only needed for typing
    from torch import nn

    from nemsim.scenes import Scene

log = logging.getLogger(__name__)

N_SURFACE_SAMPLES = 20_000  # [supp_protocols]
CHANNEL_NAMES = ("mask", "si")


def _np(a: Any) -> np.ndarray:
    """numpy view of an array or a (CPU, detached) torch tensor."""
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a)


# ---------------------------------------------------------------------------------------------
# Field errors
# ---------------------------------------------------------------------------------------------


def case_step_mse(pred: Any, true: Any) -> np.ndarray:
    """e_{i,t} of eq:supp_case_step_mse.

    Args:
        pred, true: (N, T, C, D, H, W) normalized states (any trailing state shape works).
    Returns:
        (N, T) float64 mean squared error over the state tensor's elements. Two torch tensors on an
        accelerator are compared there (the same float64 sums, without copying the states to the host).
    """
    if all(hasattr(a, "detach") and a.device.type != "cpu" for a in (pred, true)):
        import torch

        if pred.shape != true.shape or pred.dim() < 3:
            raise ValueError(f"pred shape {tuple(pred.shape)} and true shape {tuple(true.shape)}: expected "
                             "equal (N, T, ...state) shapes")
        rows = [(pred[i].detach().double() - true[i].double()).flatten(1).pow(2).mean(dim=1)
                for i in range(pred.shape[0])]  # one case at a time keeps the float64 temporary small
        return torch.stack(rows).cpu().numpy()
    p, t = _np(pred), _np(true)
    if p.shape != t.shape:
        raise ValueError(f"pred shape {p.shape} != true shape {t.shape}")
    if p.ndim < 3:
        raise ValueError(f"expected (N, T, ...state) arrays, got shape {p.shape}")
    n, steps = p.shape[:2]
    out = np.empty((n, steps), dtype=np.float64)
    for i in range(n):  # one case at a time keeps the float64 temporary small
        diff = p[i].reshape(steps, -1).astype(np.float64) - t[i].reshape(steps, -1)
        out[i] = np.einsum("tv,tv->t", diff, diff) / diff.shape[1]
    return out


def rmse_per_step(pred: Any, true: Any) -> np.ndarray:
    """RMSE_t of eq:supp_step_rmse: mean over cases of e_{i,t}, then the square root.

    Args:
        pred, true: (N, T, 2, D, H, W). T indexes whatever steps are passed (a rollout including its
            initial state gives RMSE_0 = 0 first).
    Returns:
        (T,) float64.
    """
    return np.sqrt(case_step_mse(pred, true).mean(axis=0))


def _rmse_t(pred_or_rmse: Any, true: Any | None, skip_initial: bool) -> np.ndarray:
    if true is None:
        r = _np(pred_or_rmse).astype(np.float64)
        if r.ndim != 1:
            raise ValueError(f"expected RMSE_t of shape (T,), got {r.shape}; or pass (pred, true)")
    else:
        r = rmse_per_step(pred_or_rmse, true)
    if skip_initial:
        r = r[1:]
    if r.size == 0:
        raise ValueError("no steps to average")
    return r


def avg_rmse(pred_or_rmse: Any, true: Any | None = None, *, skip_initial: bool = False) -> float:
    """Avg RMSE of eq:supp_avg_rmse = mean over steps of RMSE_t (the H = 100 predicted steps).

    Args:
        pred_or_rmse: (N, T, 2, D, H, W) predictions, or an already computed RMSE_t array (T,).
        true: (N, T, 2, D, H, W) reference, or None when the first argument is RMSE_t.
        skip_initial: drop index 0 first; use it when the arrays hold a rollout's T+1 states including
            the (copied) initial state, so that the average runs over t = 1..H as in the paper.
    """
    return float(_rmse_t(pred_or_rmse, true, skip_initial).mean())


def final_rmse(pred_or_rmse: Any, true: Any | None = None) -> float:
    """Final RMSE of eq:supp_final_rmse = RMSE_H (the last step passed)."""
    return float(_rmse_t(pred_or_rmse, true, False)[-1])


class StepRmse:
    """Streaming RMSE_t: accumulate per-step squared errors batch by batch (a `paper` test set does not fit
    in memory), then read RMSE_t / Avg / Final. Same numbers as :func:`rmse_per_step` on the concatenation.
    """

    def __init__(self) -> None:
        self._sum: np.ndarray | None = None  # (T,) sum over cases of e_{i,t}
        self.n_cases = 0

    def update(self, pred: Any, true: Any) -> None:
        """pred, true: (B, T, 2, D, H, W)."""
        e = case_step_mse(pred, true).sum(axis=0)
        if self._sum is None:
            self._sum = e
        elif self._sum.shape != e.shape:
            raise ValueError(f"step count changed: {self._sum.shape[0]} then {e.shape[0]}")
        else:
            self._sum = self._sum + e
        self.n_cases += _np(pred).shape[0]

    def rmse_per_step(self) -> np.ndarray:
        if self._sum is None:
            raise ValueError("StepRmse has no data; call update() first")
        return np.sqrt(self._sum / self.n_cases)

    def avg(self, *, skip_initial: bool = False) -> float:
        return avg_rmse(self.rmse_per_step(), skip_initial=skip_initial)

    def final(self) -> float:
        return final_rmse(self.rmse_per_step())


# ---------------------------------------------------------------------------------------------
# Chamfer distance
# ---------------------------------------------------------------------------------------------


def channel_crop(scene: Scene, channel: int) -> slice:
    """Depth slice of the CD crop of one channel (the scene's inclusive ranges -> a half-open slice)."""
    if channel == 0:
        lo, hi = scene.mask_crop
    elif channel == 1:
        lo, hi = scene.si_crop
    else:
        raise ValueError(f"channel={channel}; expected 0 (mask) or 1 (si)")
    return slice(lo, hi + 1)


def sample_surface_points(
    field: np.ndarray, seed: Sequence[int], n: int = N_SURFACE_SAMPLES
) -> tuple[np.ndarray, bool]:
    """Points on the zero level set of one cropped SDF, in voxel (crop-index) units.

    Args:
        field: (d, H, W) cropped SDF (normalized or not; only the zero level matters).
        seed: entropy for ``np.random.default_rng`` - (case_id, step, channel).
        n: samples drawn from the marching-cubes mesh, area-weighted.
    Returns:
        (points (n, 3) or (k, 3) on fallback, used_fallback).
    """
    from skimage.measure import marching_cubes

    f = np.ascontiguousarray(field, dtype=np.float32)
    lo, hi = float(f.min()), float(f.max())
    if lo < 0.0 < hi:
        verts, faces, _, _ = marching_cubes(f, level=0.0, spacing=(1.0, 1.0, 1.0), allow_degenerate=True)
        verts = verts.astype(np.float64)
        a = verts[faces[:, 0]]
        ab = verts[faces[:, 1]] - a
        ac = verts[faces[:, 2]] - a
        area = 0.5 * np.linalg.norm(np.cross(ab, ac), axis=1)  # (F,)
        cum = np.cumsum(area)
        total = cum[-1] if cum.size else 0.0
        if total > 0.0:
            rng = np.random.default_rng([int(s) for s in seed])
            tri = np.searchsorted(cum, rng.random(n) * total, side="right")
            np.minimum(tri, len(cum) - 1, out=tri)  # guards the r*total == total rounding edge
            r = rng.random((n, 2))
            flip = r.sum(axis=1) > 1.0  # reflect into the triangle: uniform barycentric sampling
            r[flip] = 1.0 - r[flip]
            pts = a[tri] + r[:, :1] * ab[tri] + r[:, 1:] * ac[tri]
            return pts, False
    # deterministic fallback: centres of the voxels with the smallest |SDF|
    absf = np.abs(f)
    idx = np.argwhere(absf == absf.min())
    return idx.astype(np.float64), True


def _tree(points: np.ndarray):
    from scipy.spatial import cKDTree

    # unbalanced, non-compact trees build faster and query about as fast for surface samples
    return cKDTree(points, leafsize=32, balanced_tree=False, compact_nodes=False)


@dataclass
class _Surface:
    points: np.ndarray  # (n, 3)
    fallback: bool
    tree: Any = None

    def kdtree(self):
        if self.tree is None:
            self.tree = _tree(self.points)
        return self.tree


def _surface(field: np.ndarray, seed: tuple[int, int, int]) -> _Surface:
    pts, fb = sample_surface_points(field, seed)
    return _Surface(pts, fb)


def _cd(p: _Surface, q: _Surface, workers: int) -> float:
    """eq:supp_chamfer_distance between two sampled surfaces."""
    d_pq, _ = q.kdtree().query(p.points, k=1, workers=workers)
    d_qp, _ = p.kdtree().query(q.points, k=1, workers=workers)
    return 0.5 * (float(d_pq.mean()) + float(d_qp.mean()))


def _check_state(a: np.ndarray, scene: Scene, what: str) -> None:
    if a.shape != scene.state_shape:
        raise ValueError(f"{what} shape {a.shape} != scene {scene.name!r} state shape {scene.state_shape}")


def chamfer_channels(
    pred: Any,
    true: Any,
    scene: Scene,
    case_id: int,
    step: int,
    *,
    cache: dict | None = None,
    workers: int = 1,
) -> tuple[float, float]:
    """Channel-wise CD (mask, si) of one state pair, voxel units. See :func:`chamfer_distance`."""
    p, t = _np(pred), _np(true)
    _check_state(p, scene, "pred")
    _check_state(t, scene, "true")
    out = []
    for c in (0, 1):
        sl = channel_crop(scene, c)
        fp, ft = p[c, sl], t[c, sl]
        seed = (int(case_id), int(step), c)
        key = (*seed, scene.name)
        ref = cache.get(key) if cache is not None else None
        if ref is None:
            ref = _surface(ft, seed)
            if cache is not None:
                cache[key] = ref
        if np.array_equal(fp, ft):  # identical crops, identical seed -> identical samples
            out.append(0.0)
            continue
        out.append(_cd(_surface(fp, seed), ref, workers))
    return out[0], out[1]


def chamfer_distance(
    pred: Any,
    true: Any,
    scene: Scene,
    case_id: int,
    step: int,
    *,
    cache: dict | None = None,
    workers: int = 1,
) -> float:
    """Chamfer distance of one state (eq:supp_chamfer_distance), mean of the mask and Si channels.

    Args:
        pred, true: (2, D, H, W) normalized SDF states of ``scene``.
        scene: gives the CD crops (``mask_crop`` for channel 0, ``si_crop`` for channel 1, inclusive).
        case_id, step: trajectory index and rollout step; with the channel they seed the sampling.
        cache: optional dict reused across calls (e.g. across models) to keep the reference surfaces'
            samples and KD-trees, keyed by (case_id, step, channel, scene name). The reference surface
            must then be the same array for a given key.
        workers: cKDTree query threads (1 on shared machines; -1 = all cores).
    Returns:
        CD in voxel units (spacing (1, 1, 1)).
    """
    cm, cs = chamfer_channels(pred, true, scene, case_id, step, cache=cache, workers=workers)
    return 0.5 * (cm + cs)


def chamfer_matrix(
    pred: Any,
    true: Any,
    scene: Scene,
    case_ids: Sequence[int],
    steps: Sequence[int] | None = None,
    *,
    cache: dict | None = None,
    workers: int = 1,
) -> np.ndarray:
    """CD for every (case, step) pair.

    Args:
        pred, true: (N, S, 2, D, H, W) or (N, 2, D, H, W) (then S = 1).
        case_ids: (N,) trajectory indices (seeds).
        steps: (S,) rollout step of each slice along axis 1; default: 0..S-1 when S > 1, and
            ``scene.n_transitions`` (the final state) for (N, 2, D, H, W) input.
    Returns:
        (N, S) CD in voxel units (or (N,) for (N, 2, D, H, W) input).
    """
    p, t = _np(pred), _np(true)
    if p.shape != t.shape:
        raise ValueError(f"pred shape {p.shape} != true shape {t.shape}")
    single = p.ndim == 5
    if single:
        p, t = p[:, None], t[:, None]
        if steps is None:
            steps = [scene.n_transitions]
    if p.ndim != 6:
        raise ValueError(f"expected (N, S, 2, D, H, W) or (N, 2, D, H, W), got {p.shape}")
    n, s = p.shape[:2]
    if steps is None:
        steps = list(range(s))
    if len(case_ids) != n or len(steps) != s:
        raise ValueError(f"need {n} case_ids and {s} steps, got {len(case_ids)} and {len(steps)}")
    out = np.empty((n, s), dtype=np.float64)
    for i in range(n):
        for j in range(s):
            out[i, j] = chamfer_distance(
                p[i, j], t[i, j], scene, case_ids[i], steps[j], cache=cache, workers=workers
            )
    return out[:, 0] if single else out


def mean_chamfer(
    pred: Any,
    true: Any,
    scene: Scene,
    case_ids: Sequence[int],
    steps: Sequence[int] | None = None,
    *,
    cache: dict | None = None,
    workers: int = 1,
) -> float:
    """Mean CD over (cases, steps); the paper reports the final step averaged over test trajectories.

    Same arguments as :func:`chamfer_matrix`.
    """
    return float(chamfer_matrix(pred, true, scene, case_ids, steps, cache=cache, workers=workers).mean())


# ---------------------------------------------------------------------------------------------
# Parameters
# ---------------------------------------------------------------------------------------------


def count_params(module: nn.Module) -> int:
    """Trainable scalar parameters (eq:supp_params, before the /1e6): shared tensors counted once,
    buffers (fixed rule tensors) and frozen parameters excluded; a complex parameter (Fourier weights) counts
    as two real scalars, as in the caption of tab:supp_baseline_impl."""
    seen: set[int] = set()
    total = 0
    for p in module.parameters():  # parameters() already skips duplicates; the set guards aliasing
        if p.requires_grad and id(p) not in seen:
            seen.add(id(p))
            total += p.numel() * (2 if p.is_complex() else 1)
    return int(total)
