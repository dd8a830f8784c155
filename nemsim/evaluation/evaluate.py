"""Test-time evaluation: the 100-step autoregressive protocol and the paper's metrics ([supp_protocols]).

Rollouts start from the ground-truth x_0 (``nemsim.evaluation.rollout``); the only correction is the monotone
projection the model's config asks for (NEMSim: on; ``nemsim.model.monotone``). They run in PyTorch f32 (the
reference) or through a compiled runtime (``predictor``: e.g. the OpenVINO graph the service runs, so
what is served is what is scored). Metrics come from ``nemsim.evaluation.metrics`` (RMSE_t over cases then
√, eqs. supp_step_rmse / supp_avg_rmse / supp_final_rmse; final-step Chamfer distance,
eq. supp_chamfer_distance; trainable parameters, eq. supp_params).

Cases are streamed in batches so memory stays at one batch of trajectories: the per-step MSE is
accumulated as Σ_i e_{i,t} (metrics.case_step_mse summed over the batch), which equals the paper's
MSE_t over all cases. Choices where the paper is silent:
  * ``rollout_seconds`` is the wall time of the model rollouts only (no data loading, no metrics), summed
    over all test cases at the given batch size; ``rollout_seconds_per_case`` divides it by N.
  * the example figure shows the first evaluated case, Si channel, the x-z slice through the opening axis,
    with the mask zero level drawn on top.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from nemsim.evaluation import metrics
from nemsim.evaluation.figure import pyplot, save_figure
from nemsim.evaluation.metrics import case_step_mse, chamfer_distance, count_params
from nemsim.evaluation.rollout import rollout
from nemsim.scenes import Scene

log = logging.getLogger(__name__)

Trajectory = tuple[int, Any, Any]  # (case_id, states (T+1, 2, D, H, W), u (T, 14) normalized)


@dataclass
class EvalResult:
    avg_rmse: float
    final_rmse: float
    cd: float | None  # mean final-step Chamfer distance, voxels (None if not computed)
    params: int  # trainable scalars
    rollout_seconds: float
    rollout_seconds_per_case: float
    rmse_per_step: list[float]  # RMSE_t, t = 1..steps
    n_cases: int
    steps: int
    case_ids: list[int]
    cd_per_case: list[float] = field(default_factory=list)
    runtime: str = "torch-f32"  # <backend>-<precision> that ran the rollouts (``nemsim.inference.runtime``)
    example: dict[str, Any] | None = field(default=None, repr=False)  # arrays for the figure

    def to_json_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d.pop("example")
        return d


def batched(items: Iterable[Trajectory], batch_size: int) -> Iterator[list[Trajectory]]:
    batch: list[Trajectory] = []
    for item in items:
        batch.append(item)
        if len(batch) == batch_size:
            yield batch
            batch = []
    if batch:
        yield batch


def _stack(batch: Sequence[Trajectory], steps: int | None, device: torch.device) -> tuple:
    case_ids = [int(c) for c, _, _ in batch]
    def tensor(a: Any) -> torch.Tensor:  # a tensor stays where it is (an in-memory set on the device)
        return a.float() if isinstance(a, torch.Tensor) else torch.as_tensor(np.asarray(a),
                                                                             dtype=torch.float32)

    states = torch.stack([tensor(s) for _, s, _ in batch])
    u = torch.stack([tensor(uu) for _, _, uu in batch])
    T = u.shape[1] if steps is None else steps
    if T > u.shape[1] or T + 1 > states.shape[1]:
        raise ValueError(f"steps={T} exceeds the trajectory length ({states.shape[1]} states)")
    return case_ids, states[:, : T + 1], u[:, :T].to(device), T  # (B,T+1,2,D,H,W), (B,T,14)


def step_sq_error_sum(pred: torch.Tensor, true: torch.Tensor) -> np.ndarray:
    """Σ_i e_{i,t} over the batch for t = 1..T (pred/true (B, T+1, 2, D, H, W), step 0 excluded),
    computed through metrics.case_step_mse so the metric definition lives in one place (on the device
    when both are there)."""
    p, t = pred[:, 1:].detach().float(), true[:, 1:].detach().float()
    if p.device != t.device or p.device.type == "cpu":
        p, t = p.cpu(), t.cpu()
    return case_step_mse(p, t).sum(axis=0)  # (T,) float64


def rollout_errors(
    model: nn.Module,
    trajectories: Iterable[Trajectory],
    *,
    steps: int | None = None,
    batch_size: int = 8,
    device: torch.device | str = "cpu",
) -> tuple[np.ndarray, int]:
    """Σ_i e_{i,t} (T,) and N for the validation monitor (no metrics beyond the field error)."""
    device = torch.device(device)
    total: np.ndarray | None = None
    n = 0
    for batch in batched(trajectories, batch_size):
        _, states, u, T = _stack(batch, steps, device)
        pred = rollout(model, states[:, 0].to(device), u, T)
        s = step_sq_error_sum(pred, states)
        total = s if total is None else total + s
        n += len(batch)
    if total is None:
        raise ValueError("no trajectories to roll out")
    return total, n


def rmse_summary(sq_error_sum: np.ndarray, n: int) -> dict[str, Any]:
    """Avg/Final RMSE from Σ_i e_{i,t}: RMSE_t = sqrt(MSE_t), Avg = mean_t RMSE_t, Final = RMSE_H."""
    rmse_t = np.sqrt(np.asarray(sq_error_sum, dtype=np.float64) / n)
    return {
        "avg_rmse": float(metrics.avg_rmse(rmse_t)),
        "final_rmse": float(metrics.final_rmse(rmse_t)),
        "mse": float(np.mean(rmse_t**2)),
        "rmse_per_step": [float(v) for v in rmse_t],
    }


class RolloutWriter:
    """Streams predicted trajectories to HDF5: ``pred`` (N, T+1, 2, D, H, W) with x_0 first, ``case_ids``."""

    def __init__(self, path: str | Path, n_cases: int, steps: int, scene: Scene, attrs: dict | None = None):
        import h5py

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = h5py.File(self.path, "w")
        shape = (n_cases, steps + 1, *scene.state_shape)
        self._pred = self._f.create_dataset(
            "pred", shape=shape, dtype="float32", chunks=(1, 1, *scene.state_shape), compression="lzf"
        )
        self._ids = self._f.create_dataset("case_ids", shape=(n_cases,), dtype="int64")
        self._f.attrs["scene"] = scene.to_json()
        self._f.attrs["channel_names"] = ["mask", "si"]
        for k, v in (attrs or {}).items():
            self._f.attrs[k] = v
        self._row = 0

    def write(self, case_ids: Sequence[int], pred: torch.Tensor) -> None:
        b = len(case_ids)
        self._pred[self._row : self._row + b] = pred.detach().float().cpu().numpy()
        self._ids[self._row : self._row + b] = np.asarray(case_ids, dtype=np.int64)
        self._row += b

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "RolloutWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def evaluate(
    model: nn.Module,
    trajectories: Sequence[Trajectory],
    scene: Scene,
    *,
    steps: int | None = None,
    batch_size: int = 1,
    device: torch.device | str = "cpu",
    chamfer: bool = True,
    rollout_path: str | Path | None = None,
    rollout_attrs: dict | None = None,
    predictor: Any = None,
) -> EvalResult:
    """Evaluate a one-step model on test trajectories with the full autoregressive protocol.

    Args:
        model: the surrogate (eval mode is set here).
        trajectories: indexable of (case_id, states (T+1, 2, D, H, W), u (T, 14) normalized), e.g. a
            ``TrajectoryDataset``.
        scene: the scene (Chamfer crops).
        steps: transitions to roll out (default: all, 100).
        batch_size: trajectories rolled out together (1 = the paper's per-trajectory timing).
        chamfer: compute the final-step Chamfer distance (the slowest metric).
        rollout_path: if given, stream predictions to this HDF5 file (``pred``, ``case_ids``).
        predictor: a runtime of ``model`` (``nemsim.inference.runtime.compile_model``, e.g. the served
            OpenVINO graph) that runs the rollouts instead of the model itself; CPU only. Its graph is
            compiled for the first batch's shape before the timing starts (a smaller last batch compiles
            its own shape inside it).
    """
    device = torch.device(device)
    model = model.to(device).eval()
    on_gpu = getattr(predictor, "backend", None) == "cuda"  # the CUDA-graph runtime holds its own model copy
    if predictor is not None and (device.type != "cpu") != on_gpu:
        where = "a CUDA device" if on_gpu else "the CPU only"
        raise ValueError(f"the {getattr(predictor, 'backend', '?')} runtime runs on {where}, not on {device}")
    stepper = model if predictor is None else predictor
    n_total = len(trajectories)
    if n_total == 0:
        raise ValueError("no test trajectories to evaluate")
    first_T = len(trajectories[0][2])  # transitions of the first case's controls (an array or a tensor)
    T_run = first_T if steps is None else steps
    writer = RolloutWriter(rollout_path, n_total, T_run, scene, rollout_attrs) if rollout_path else None
    sq_sum: np.ndarray | None = None
    seconds = 0.0
    case_ids: list[int] = []
    cds: list[float] = []
    example = None
    try:
        for batch in batched((trajectories[i] for i in range(n_total)), batch_size):
            ids, states, u, T = _stack(batch, T_run, device)
            x0 = states[:, 0].to(device)
            if predictor is not None and not case_ids:  # compile the graph for this batch shape, untimed
                rollout(stepper, x0, u, 1, keep=False)
            t0 = time.perf_counter()
            pred = rollout(stepper, x0, u, T)  # (B, T+1, 2, D, H, W)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds += time.perf_counter() - t0
            pred, states = pred.float().cpu(), states.cpu()  # the metrics below read host arrays
            s = step_sq_error_sum(pred, states)
            sq_sum = s if sq_sum is None else sq_sum + s
            if chamfer:
                for b, cid in enumerate(ids):
                    cds.append(
                        float(chamfer_distance(pred[b, -1].numpy(), states[b, -1].numpy(), scene, cid, T))
                    )
            if writer is not None:
                writer.write(ids, pred)
            if example is None:
                example = {
                    "case_id": ids[0],
                    "truth": states[0, -1].numpy().copy(),
                    "pred": pred[0, -1].numpy().copy(),
                }
            case_ids.extend(ids)
            log.debug("evaluated %d/%d cases", len(case_ids), n_total)
    finally:
        if writer is not None:
            writer.close()
    assert sq_sum is not None
    summary = rmse_summary(sq_sum, len(case_ids))
    return EvalResult(
        avg_rmse=summary["avg_rmse"],
        final_rmse=summary["final_rmse"],
        cd=float(np.mean(cds)) if cds else None,
        params=int(count_params(model)),
        rollout_seconds=seconds,
        rollout_seconds_per_case=seconds / len(case_ids),
        rmse_per_step=summary["rmse_per_step"],
        n_cases=len(case_ids),
        steps=T_run,
        case_ids=case_ids,
        cd_per_case=cds,
        runtime="torch-f32" if predictor is None else f"{predictor.backend}-{predictor.precision}",
        example=example,
    )


def write_json(result: EvalResult, path: str | Path, extra: dict | None = None) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({**result.to_json_dict(), **(extra or {})}, indent=2))


def plot_evaluation(result: EvalResult, scene: Scene, path: str | Path, title: str = "") -> Path:
    """PNG: RMSE_t over the rollout, and the final-step slice (truth, prediction, |error|) of the Si
    channel through the opening axis (x-z plane at the centre y), mask zero level overlaid."""
    plt = pyplot()

    fig = plt.figure(figsize=(12, 7.5))
    gs = fig.add_gridspec(2, 3, height_ratios=[1.0, 1.4])
    ax = fig.add_subplot(gs[0, :])
    steps = np.arange(1, len(result.rmse_per_step) + 1)
    ax.plot(steps, result.rmse_per_step, lw=1.5)
    ax.set_xlabel("rollout step t")
    ax.set_ylabel("RMSE$_t$ (normalized SDF)")
    ax.set_title(
        f"{title} Avg RMSE {result.avg_rmse:.4f}  Final RMSE {result.final_rmse:.4f}"
        + (f"  CD {result.cd:.3f} vox" if result.cd is not None else "")
    )
    ax.grid(alpha=0.3)
    if result.example is not None:
        h = scene.field_shape[1] // 2
        truth = result.example["truth"][:, :, h, :]  # (2, D, W)
        pred = result.example["pred"][:, :, h, :]
        err = np.abs(pred - truth)
        panels = [("truth", truth, "RdBu", (-1, 1)), ("prediction", pred, "RdBu", (-1, 1)),
                  ("|error|", err, "magma", (0, max(float(err[1].max()), 1e-6)))]
        for k, (name, field_, cmap, (lo, hi)) in enumerate(panels):
            a = fig.add_subplot(gs[1, k])
            im = a.imshow(field_[1], origin="lower", cmap=cmap, vmin=lo, vmax=hi, aspect="equal")
            if name != "|error|":
                a.contour(field_[1], levels=[0.0], colors="k", linewidths=0.8)
                a.contour(field_[0], levels=[0.0], colors="tab:orange", linewidths=0.8)
            a.set_title(f"case {result.example['case_id']} step {result.steps}: Si {name}")
            a.set_xlabel("x (voxels)")
            a.set_ylabel("depth index")
            fig.colorbar(im, ax=a, fraction=0.046)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110)
