"""The training loop ([supp_training], [supp_evaluation], eq. training_loss): one function, top to bottom.

One-step supervision (the paper): minimize the voxel-wise MSE between F_θ(x_t, u_t) and x_{t+1} on normalized
fields. The terms beyond the paper (pushforward unrolls, multi-step targets, profile and pair losses) are
described with their fields in ``TrainConfig``.

Every ``val_every`` epochs the model is rolled out autoregressively from x_0 over the full horizon on the
validation trajectories (no gradient); the best rollout is kept as ``best.pt`` and training stops after
``patience`` validation rounds without improvement (with ``ema_decay``: the moving-average weights).
``last.pt`` is written after every epoch (and every ``checkpoint_every`` steps) with the optimizer, schedule
step, RNG states, history and the position in the unfinished epoch (``RunState``), so a killed run resumes
where it was saved and reproduces the uninterrupted run (shuffling is a pure function of seed and epoch).
Wall and CPU time are summed over resumes in ``last.pt``, so ``max_train_minutes`` spans them; time is read
through a ``Clock`` (tests pass a deterministic one).

DDP: if ``torch.distributed`` is initialized (``torchrun``) the model is wrapped in DistributedDataParallel,
each rank sees a disjoint shard of every epoch (per-rank batch = batch_size / world size), validation
trajectories are sharded and their error sums all-reduced, every rank uses rank 0's wall time (same
learning rate, same stop); only rank 0 writes files.

Outputs in ``out_dir``: ``best.pt``, ``last.pt``, ``metrics.csv`` (one row per epoch: step, lr, train loss,
validation metrics when computed, seconds, and the run's cumulative ``wall_s`` / ``cpu_s`` / ``val_wall_s``
at the row's weights: the x axis of an error-against-training-time curve) and ``summary.json``.
"""

from __future__ import annotations

import csv
import itertools
import json
import logging
import math
import random
import time
from collections.abc import Callable, Sized
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DataLoader, Dataset, Sampler
from torch.utils.data.distributed import DistributedSampler

from nemsim.data.dataset import as_batch
from nemsim.evaluation.evaluate import rmse_summary, rollout_errors
from nemsim.evaluation.rollout import steps_per_call
from nemsim.inference.checkpoint import checkpoint_dict, read_checkpoint, unwrap, write_checkpoint_dict
from nemsim.inference.precision import native_bf16
from nemsim.scenes import Scene
from nemsim.training.average import WeightAverage
from nemsim.training.config import TrainConfig

log = logging.getLogger(__name__)

CSV_FIELDS = ("epoch", "step", "lr", "train_loss", "val_avg_rmse", "val_final_rmse", "val_mse",
              "epoch_seconds", "val_seconds", "wall_s", "cpu_s", "val_wall_s")
FINAL_LOSS_STEPS = 50  # the summary's final training loss is the mean over this many last steps
BAR_EVERY = 10  # steps between progress-bar updates (each reads the loss from the device)


@dataclass(frozen=True)
class Clock:
    """Where the loop reads time: wall seconds (every timing, the wall budget and, under a budget, the
    learning-rate horizon) and CPU seconds of this process (reported beside them). Tests pass a
    deterministic wall clock so a budget ends at a known step."""

    wall: Callable[[], float] = time.perf_counter
    cpu: Callable[[], float] = time.process_time


@dataclass
class TrainData:
    """train: items (x_t (2,D,H,W), u_t (14,), x_{t+1}); val: indexable of (case_id, states, u);
    pairs: optional sweep pairs (``nemsim.data.dataset.PairDataset``, the same items stacked per pair)."""

    train: Dataset
    val: Any
    pairs: Dataset | None = None


@dataclass
class ModelMeta:
    """What a checkpoint needs to rebuild the model (see nemsim.inference.checkpoint)."""

    name: str
    config: dict[str, Any]
    scene: Scene
    rules: Any  # RuleTensors
    rules_perturbation: dict[str, Any] | None = None
    sim_config: dict[str, Any] | None = None  # the data file's simulator configuration (``generator``)
    # where the weights came from, written into every summary: ``init_from`` (None: random weights),
    # ``recipe`` (its path, under `nemsim train --recipe`), ``data`` (each file, its cases, a digest)
    provenance: dict[str, Any] = field(default_factory=dict)


def total_steps(steps_per_epoch: int, cfg: TrainConfig) -> int:
    """The run's optimizer-step budget: max_epochs epochs, or max_steps if that is smaller."""
    total = cfg.max_epochs * steps_per_epoch
    return total if cfg.max_steps is None else min(total, cfg.max_steps)


def lr_at(step: int, steps_per_epoch: int, cfg: TrainConfig, wall_s: float = 0.0) -> float:
    """Linear warm-up (``warmup_steps``, else ``warmup_epochs``) then half-cosine from lr to min_lr at the
    end of the budget (``total_steps``).

    With a wall budget (``max_train_minutes``) the cosine's progress is the fraction of the budget spent,
    ``wall_s`` / budget (min_lr once it is spent), and the warm-up multiplies the cosine's value by
    (step + 1) / warm-up steps: one curve, continuous at the warm-up's end, whatever the model's speed.
    """
    warm = cfg.warmup_steps if cfg.warmup_steps is not None else cfg.warmup_epochs * steps_per_epoch
    if cfg.max_train_minutes is not None:
        progress = min(max(wall_s, 0.0) / (60.0 * cfg.max_train_minutes), 1.0)
        value = cfg.min_lr + 0.5 * (cfg.lr - cfg.min_lr) * (1.0 + math.cos(math.pi * progress))
        return value * (step + 1) / warm if step < warm else value
    total = max(total_steps(steps_per_epoch, cfg), warm + 1)
    if step < warm:
        return cfg.lr * (step + 1) / warm
    progress = min((step - warm) / max(total - warm, 1), 1.0)
    return cfg.min_lr + 0.5 * (cfg.lr - cfg.min_lr) * (1.0 + math.cos(math.pi * progress))


def pushforward_loss(model: nn.Module, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor, autocast,
                     memory_format=torch.contiguous_format, detach: bool = True) -> torch.Tensor:
    """Mean of k one-step MSEs along a k-transition window, each step fed the previous detached prediction.

    x (B, 2, D, H, W) = x_t; u (B, k, 14); y (B, k, 2, D, H, W) = x_{t+1..t+k}. Gradients flow only
    through each single step (no backpropagation through time): cost and memory are those of k steps.
    ``detach`` False: each step is fed the prediction itself, and gradients flow through the whole chain.
    """
    k = u.shape[1]
    state, total = x, cast(Any, 0.0)  # a tensor after the first step
    for j in range(k):
        with autocast:
            pred = model(state.contiguous(memory_format=memory_format), u[:, j])
        pred = pred.float()
        total = total + torch.mean((pred - y[:, j]) ** 2)
        state = pred.detach() if detach else pred
    return total / k


PROFILE_LOSS_METRICS = ("etch_depth", "top_width", "bottom_width", "mask_loss")


def _is_section(states: torch.Tensor, scene: Scene) -> bool:
    """Whether states (N, 2, D, H, W) are a section-domain model's cross-sections (a trench's)."""
    return states.shape[-1] != scene.state_shape[-1] and states.shape[-2] != states.shape[-1]


def full_states(states: torch.Tensor, scene: Scene) -> torch.Tensor:
    """States (N, 2, D, H, W) of the full scene: a quarter-domain model's quadrants (N, 2, D, c, c) (or a
    section-domain model's cross-sections (N, 2, D, 2, c)) are rebuilt by reflection
    (``nemsim.symmetry``, differentiable), full states pass through."""
    from nemsim.symmetry import unfold, unfold_section

    n = scene.state_shape[-1]
    if _is_section(states, scene):
        return unfold_section(states, n)
    return states if states.shape[-1] == n else unfold(states, n)


def section_si_tops(q: torch.Tensor, scene: Scene) -> torch.Tensor:
    """(N,) each trench's Si top (``Scene.si_top``: its own mask thickness) read from its cross-sections q
    (N, 2, D, r, c): the Si voxels of the column at the pitch's edge (native x = 0), under the mask and never
    etched, clamped to the tops a feature may have (``nemsim.geometry.feature``)."""
    from nemsim.geometry.feature import MIN_SI_FRACTION

    si = q[:, 1, 1 : scene.nz + 1, 0, 1]  # (N, nz): the edge column (rows are equal)
    lo = math.ceil(MIN_SI_FRACTION * scene.si_top)
    return (si < 0).sum(dim=1).clamp(lo, scene.resist_top - 1)


def _profile_voxels(states: torch.Tensor, scene: Scene, tops: torch.Tensor | None = None) -> torch.Tensor:
    """(4, N) soft profile metrics (``PROFILE_LOSS_METRICS``) in voxels of states (N, 2, D, H, W), full,
    quadrant or cross-section. A trench's cross-sections are measured as trenches, each at its own Si top
    (``tops`` (N,), default ``section_si_tops`` of the states): a trench's mask, so its top row, is a case's
    own, while the data file's scene holds one feature (whose opening sets the mask-loss columns: depth and
    widths are read on the axis and do not depend on it). They are grouped by top and each group unfolded
    as a view (its line repeated along y), so the cost stays that of the cross-sections."""
    from nemsim.geometry.feature import Feature
    from nemsim.geometry.soft_profile import soft_profile_metrics
    from nemsim.symmetry import section_line

    if not _is_section(states, scene):
        m = soft_profile_metrics(full_states(states, scene), scene)
        return torch.stack([m[k] / scene.voxel_nm for k in PROFILE_LOSS_METRICS])
    tops = section_si_tops(states, scene) if tops is None else tops
    n = scene.state_shape[-1]
    cd = 2.0 * scene.opening_radius_vox * scene.voxel_nm
    parts, order = [], []
    for top in tops.unique().tolist():
        idx = torch.nonzero(tops == top).squeeze(1)
        group = section_line(states.index_select(0, idx), n)  # (g, 2, D, 1, n)
        case = Feature("trench", cd, (scene.resist_top - top) * scene.voxel_nm).apply(scene)
        m = soft_profile_metrics(group.expand(*group.shape[:-2], n, n), case)
        parts.append(torch.stack([m[k] / scene.voxel_nm for k in PROFILE_LOSS_METRICS]))
        order.append(idx)
    return torch.cat(parts, dim=1)[:, torch.argsort(torch.cat(order))]


def profile_loss(pred: torch.Tensor, target: torch.Tensor, scene: Scene) -> torch.Tensor:
    """Mean squared error in voxels^2 of the soft profile metrics (``PROFILE_LOSS_METRICS``) of pred (N, 2, D,
    H, W) against target (N, 2, D, H, W) (full states, or a quarter- or section-domain model's fields; a
    trench's measured at the target's Si top), float32; the training config's ``profile_loss_weight`` term."""
    tops = section_si_tops(target, scene) if _is_section(target, scene) else None
    return torch.mean((_profile_voxels(pred, scene, tops) - _profile_voxels(target, scene, tops)) ** 2)


def pair_loss(pred: torch.Tensor, target: torch.Tensor, n_pairs: int) -> torch.Tensor:
    """MSE of the predicted pair differences against the simulated ones: the last 2P samples of pred and
    target (N, ...) are P pairs, the P first members then the P second ones
    (``TrainConfig.pair_loss_weight``).
    """
    p = n_pairs
    d_pred = pred[-p:] - pred[-2 * p:-p]  # (P, ...)
    d_true = target[-p:] - target[-2 * p:-p]
    return torch.mean((d_pred - d_true) ** 2)


def response_loss(pred: torch.Tensor, target: torch.Tensor, n_pairs: int, scene: Scene) -> torch.Tensor:
    """MSE in voxels^2 of the pairs' predicted profile-metric differences against the simulated ones
    (``TrainConfig.response_loss_weight``): the last 2P samples of pred and target (N, [k,] 2, D, H, W) are
    P pairs as in ``pair_loss``; with k states per sample every state's metrics count."""
    p = n_pairs

    def responses(states: torch.Tensor) -> torch.Tensor:
        m = _profile_voxels(states[-2 * p:].reshape(-1, *states.shape[-4:]), scene)  # (4, 2P·k)
        half = m.shape[1] // 2  # first members, then second members, (pair, state) order in each
        return m[:, half:] - m[:, :half]

    return torch.mean((responses(pred) - responses(target)) ** 2)


@dataclass(frozen=True)
class PairTerms:
    """The sweep pairs that end a batch (``n`` pairs: the n first members, then the n second ones) and the
    weights of their two difference terms (``TrainConfig.pair_loss_weight``, ``response_loss_weight``)."""

    n: int
    field_weight: float
    response_weight: float
    scene: Scene

    def loss(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor | float:
        """λ_pair ``pair_loss`` + λ_resp ``response_loss`` of pred and target (N, [k,] 2, D, H, W)."""
        total: torch.Tensor | float = 0.0
        if self.field_weight > 0:
            total = total + self.field_weight * pair_loss(pred, target, self.n)
        if self.response_weight > 0:
            total = total + self.response_weight * response_loss(pred, target, self.n, self.scene)
        return total


def multistep_loss(model: nn.Module, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor, k: int, autocast,
                   memory_format=torch.contiguous_format,
                   weights: torch.Tensor | None = None,
                   profile: tuple[float, Scene] | None = None,
                   pairs: PairTerms | None = None, detach: bool = True) -> torch.Tensor:
    """Loss of a model predicting k states per call, over U = u.shape[1] / k calls chained by their detached
    last state (the pushforward term over calls of k; U = 1: plain k-step supervision).

    x (B, 2, D, H, W) = x_t; u (B, U·k, 14); y (B, U·k, 2, D, H, W) = x_{t+1..t+Uk}; weights (k,) per
    predicted state (None = uniform), normalized to sum 1. Call c predicts x_{t+ck+1..t+ck+k} under the
    controls of its first transition u_{t+ck} (as the rollout does with constant controls). Returns the mean
    over calls of Σ_j w_j MSE_j. With k = 1 this is ``pushforward_loss`` (model called as model(x, u)).
    ``profile`` = (lambda, scene) adds lambda times ``profile_loss`` of each call's last predicted state (the
    state the next call starts from; over a sample's random start it meets every time of the rollout, at a
    k-th of the cost of every state).
    ``pairs``: the batch ends with sweep pairs, and their difference terms (``PairTerms.loss``) over every
    predicted state are added to each call.
    ``detach`` False (``TrainConfig.unroll_grad``): call c starts from call c-1's last state itself, and
    gradients flow through the whole chain of calls.
    """
    n = u.shape[1]
    if n % k:
        raise ValueError(f"a sample of {n} transitions is not a whole number of calls of steps_per_call={k}")
    if weights is None:
        weights = torch.ones(k)
    w = (weights / weights.sum()).to(y.device)  # (k,)
    state, total = x, cast(Any, 0.0)  # a tensor after the first call
    for c in range(n // k):
        with autocast:
            xin = state.contiguous(memory_format=memory_format)
            pred = model(xin, u[:, c * k], all_steps=True) if k > 1 else model(xin, u[:, c])[:, None]
        pred = pred.float()  # (B, k, 2, D, H, W)
        per_state = torch.mean((pred - y[:, c * k:(c + 1) * k]) ** 2, dim=(0, 2, 3, 4, 5))  # (k,)
        total = total + torch.sum(w * per_state)
        if profile is not None and profile[0] > 0:
            total = total + profile[0] * profile_loss(pred[:, -1], y[:, (c + 1) * k - 1], profile[1])
        if pairs is not None:
            total = total + pairs.loss(pred, y[:, c * k:(c + 1) * k])
        state = pred[:, -1].detach() if detach else pred[:, -1]
    return total / (n // k)


def pick_device(name: str) -> torch.device:
    if name == "auto":
        if torch.cuda.is_available():
            local = int(__import__("os").environ.get("LOCAL_RANK", 0))
            return torch.device("cuda", local)
        return torch.device("cpu")
    return torch.device(name)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _rng_state() -> dict[str, Any]:
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def _set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


class _ResumableSampler(Sampler):
    """DistributedSampler whose epoch can start ``skip`` indices in: a mid-epoch resume reads only the
    batches still to train (the shuffled order itself is unchanged, so the remaining batches are
    identical). ``cap`` ends every epoch after that many indices (``TrainConfig.batches_per_epoch``): each
    epoch is then a fresh random sample of the shuffled training set."""

    def __init__(self, base: DistributedSampler, cap: int | None = None) -> None:
        self.base, self.skip = base, 0
        self.cap = len(base) if cap is None else min(cap, len(base))

    def set_epoch(self, epoch: int) -> None:
        self.base.set_epoch(epoch)

    def __iter__(self):
        return itertools.islice(iter(self.base), self.skip, self.cap)

    def __len__(self) -> int:
        return self.cap - self.skip


def _write_csv(path: Path, history: list[dict[str, Any]]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        for row in history:
            w.writerow({k: row.get(k, "") for k in CSV_FIELDS})
    tmp.replace(path)


@dataclass
class RunState:
    """What a run carries from one optimizer step to the next; ``last.pt`` stores it as ``train_state``."""

    epoch: int = 0  # epochs finished (the next epoch to train)
    step: int = 0  # optimizer steps taken (the lr-schedule step)
    best: float = math.inf  # best validation score (``select_metric``)
    best_epoch: int = -1
    bad_rounds: int = 0  # validation rounds since the last improvement
    history: list[dict[str, Any]] = field(default_factory=list)  # one metrics.csv row per finished epoch
    epoch_loss: tuple[float, float] = (0.0, 0.0)  # (Σ loss·n, n) of a partly trained epoch (mid-epoch)
    skip: int = 0  # batches of the resumed epoch already trained (mid-epoch last.pt)
    stopped_early: bool = False
    wall_s: float = 0.0  # run wall seconds before this process (stored at the resumed checkpoint)
    cpu_s: float = 0.0  # run CPU seconds before this process
    val_wall_s: float = 0.0  # wall seconds of all validation rollouts so far (part of the run's wall time)
    recent_losses: list[float] = field(default_factory=list)  # the last FINAL_LOSS_STEPS step losses
    budget_spent: bool = False  # the wall budget (max_train_minutes) is used up

    @classmethod
    def from_train_state(cls, ts: dict[str, Any], steps_per_epoch: int) -> RunState:
        """The state of a ``last.pt`` ``train_state`` (RNG states are restored by the caller)."""
        epoch, step = ts["epoch"], ts["schedule_step"]
        epoch_loss = tuple(ts.get("epoch_loss", (0.0, 0.0)))
        # count stored since mid-epoch checkpoints; epoch-end checkpoints resume at batch 0 even when the
        # steps per epoch change (e.g. a continuation with another unroll_steps)
        partly = epoch_loss[1] > 0  # only mid-epoch checkpoints carry the sums of an unfinished epoch
        skip = int(ts.get("epoch_batches", step - epoch * steps_per_epoch if partly else 0))
        return cls(epoch=epoch, step=step, best=ts["best"], best_epoch=ts["best_epoch"],
                   bad_rounds=ts["bad_rounds"], history=list(ts["history"]),
                   epoch_loss=(float(epoch_loss[0]), float(epoch_loss[1])), skip=skip,
                   wall_s=float(ts.get("wall_s", 0.0)), cpu_s=float(ts.get("cpu_s", 0.0)),
                   val_wall_s=float(ts.get("val_wall_s", 0.0)),
                   recent_losses=[float(v) for v in ts.get("recent_losses", [])])  # fmt: skip

    def train_state(self, optimizer: torch.optim.Optimizer, epoch_done: int, partial: torch.Tensor | None,
                    batches: int, wall_s: float, cpu_s: float) -> dict[str, Any]:
        """``last.pt``'s ``train_state``: ``partial`` = loss sums of an unfinished epoch of which ``batches``
        batches are trained (None at an epoch's end); ``wall_s`` / ``cpu_s`` = the run's time so far."""
        return {"optimizer": optimizer.state_dict(), "epoch": epoch_done, "schedule_step": self.step,
                "best": self.best, "best_epoch": self.best_epoch, "bad_rounds": self.bad_rounds,
                "history": self.history, "rng": _rng_state(),
                "epoch_loss": (0.0, 0.0) if partial is None else tuple(float(v) for v in partial),
                "epoch_batches": batches, "wall_s": wall_s, "cpu_s": cpu_s, "val_wall_s": self.val_wall_s,
                "recent_losses": list(self.recent_losses)}  # fmt: skip


def _check_items(cfg: TrainConfig, data: TrainData, k: int) -> int:
    """Transitions per training item (unroll_steps x steps_per_call); refuses a dataset that does not fit."""
    window = cfg.unroll_steps * k
    if getattr(data.train, "unroll", 1) != window:
        raise ValueError(f"unroll_steps={cfg.unroll_steps} x steps_per_call={k} needs a train dataset of "
                         f"{window}-transition items; got unroll={getattr(data.train, 'unroll', 1)}")
    if cfg.step_loss_weights is not None and len(cfg.step_loss_weights) != k:
        raise ValueError(f"step_loss_weights has {len(cfg.step_loss_weights)} entries; the model predicts "
                         f"steps_per_call={k} states per call")
    return window


def _train_loader(train_set: Dataset, cfg: TrainConfig, rank: int, world: int,
                  device: torch.device) -> tuple[DataLoader, _ResumableSampler, int]:
    """(loader, its sampler, per-rank batch). A DistributedSampler also for one rank, so that shuffling is a
    function of (seed, epoch) and a resumed run sees the same batches."""
    if cfg.batch_size % world:
        log.warning("batch_size %d is not divisible by world size %d", cfg.batch_size, world)
    per_rank_batch = max(1, cfg.batch_size // world)
    cap = None if cfg.batches_per_epoch is None else cfg.batches_per_epoch * per_rank_batch
    sampler = _ResumableSampler(
        DistributedSampler(train_set, num_replicas=world, rank=rank, shuffle=True, seed=cfg.seed), cap)
    batched = getattr(train_set, "batched", False)  # MemoryTransitions: whole batches by index, in memory
    on_device = batched and getattr(train_set, "device", torch.device("cpu")).type != "cpu"
    loader = DataLoader(
        train_set,
        batch_size=per_rank_batch,
        sampler=sampler,
        num_workers=0 if batched else cfg.num_workers,
        pin_memory=device.type == "cuda" and not on_device,
        persistent_workers=cfg.num_workers > 0 and not batched,
        collate_fn=as_batch if batched else None,
    )
    return loader, sampler, per_rank_batch


class _Run:
    """One training run: the fixed pieces (model, optimizer, loader, precision) and the ``RunState``."""

    def __init__(self, cfg: TrainConfig, model: nn.Module, data: TrainData, out_dir: Path,
                 meta: ModelMeta, clock: Clock) -> None:
        self.cfg, self.data, self.out_dir, self.meta, self.clock = cfg, data, out_dir, meta, clock
        self.k = steps_per_call(model)
        self.window = _check_items(cfg, data, self.k)
        self.pairs = data.pairs
        extras = [n for n, on in (("profile_loss_weight", cfg.profile_loss_weight > 0),
                                  ("sweep pairs", self.pairs is not None)) if on]
        if extras and self.k == 1 and self.window > 1:
            raise ValueError(f"{' and '.join(extras)}: implemented for the one-step and k-step losses, not "
                             "for the one-step pushforward (unroll_steps > 1 with steps_per_call 1)")
        if self.pairs is not None:
            if getattr(self.pairs, "unroll", 1) != self.window:
                held = getattr(self.pairs, "unroll", 1)
                raise ValueError(f"the pair data's items hold {held} transitions; the training items hold "
                                 f"{self.window}")
        elif cfg.pair_loss_weight > 0 or cfg.response_loss_weight > 0:
            raise ValueError("pair_loss_weight and response_loss_weight need sweep pairs to train on: give "
                             "--pair-data (made by `nemsim design --kind pairs` and `nemsim generate "
                             "--controls`)")
        self.distributed = dist.is_available() and dist.is_initialized()
        rank, world = (dist.get_rank(), dist.get_world_size()) if self.distributed else (0, 1)
        self.is_main = rank == 0
        if self.is_main:
            out_dir.mkdir(parents=True, exist_ok=True)
        # ---- device, precision, model --------------------------------------------------------------
        self.device = pick_device(cfg.device)
        self.memory_format = torch.channels_last_3d if cfg.channels_last else torch.contiguous_format
        self.model = model.to(device=self.device, memory_format=self.memory_format)  # type: ignore[call-overload]
        self.train_model: nn.Module = self.model  # DDP-wrapped by ``start``
        self.bf16 = native_bf16(self.device.type) if cfg.bf16 is None else cfg.bf16
        self.autocast = (
            torch.autocast(device_type=self.device.type, dtype=torch.bfloat16) if self.bf16 else nullcontext()
        )
        # fused on a GPU: one kernel for the whole update, where the step is launch-bound
        self.optimizer = torch.optim.AdamW(
            self.model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay,
            fused=self.device.type == "cuda",
        )
        self.step_weights = None if cfg.step_loss_weights is None else torch.tensor(cfg.step_loss_weights)
        # the weights validation sees (ema_decay > 0): their moving average; None: the trained ones
        self.average = WeightAverage(self.model, cfg.ema_decay) if cfg.ema_decay > 0 else None
        # ---- data --------------------------------------------------------------------------------------
        self.loader, self.sampler, self.per_rank_batch = _train_loader(data.train, cfg, rank, world,
                                                                       self.device)
        self.steps_per_epoch = len(self.loader)
        self.val_index = list(range(rank, len(data.val), world))  # this rank's validation trajectories
        self.world = world
        self.state = RunState()
        self.step_cap = cfg.max_steps if cfg.max_steps is not None else math.inf
        self.budget_s = None if cfg.max_train_minutes is None else 60.0 * cfg.max_train_minutes
        self.last_path, self.best_path = out_dir / "last.pt", out_dir / "best.pt"
        self.t_start, self.c_start = clock.wall(), clock.cpu()  # this process's share starts (reset by start)
        self.now_wall = 0.0  # the run's wall seconds at the last ``tick``
        self.bar: Any = None
        self.pending: list[torch.Tensor] = []  # step losses not yet read from the device (``losses``)

    def resume(self) -> None:
        """Continue from ``last.pt`` if there is one: weights, optimizer, state, RNG streams."""
        if not self.last_path.is_file():
            log.info("--resume: no %s yet, starting fresh", self.last_path)
            return
        ckpt = read_checkpoint(self.last_path)
        ts = ckpt["train_state"]
        unwrap(self.model).load_state_dict(ckpt["model_state"])
        self.optimizer.load_state_dict(ts["optimizer"])
        if self.average is not None:
            if "ema" in ts:
                self.average.load_state_dict(ts["ema"])
            else:
                log.info("--resume: %s holds no weight average; it starts at the resumed weights",
                         self.last_path)
                self.average.reset()
        self.state = RunState.from_train_state(ts, self.steps_per_epoch)
        _set_rng_state(ts["rng"])
        st = self.state
        log.info("resumed from %s at epoch %d (best %.5g at epoch %d)", self.last_path, st.epoch, st.best,
                 st.best_epoch)

    def start(self) -> None:
        """Wrap for DDP, open the progress bar, log the run's shape."""
        cfg, st = self.cfg, self.state
        if self.distributed:
            ids = [self.device.index] if self.device.type == "cuda" else None
            # The compiled rule tensors are fixed buffers: nothing to broadcast after construction.
            self.train_model = nn.parallel.DistributedDataParallel(self.model, device_ids=ids,
                                                                   broadcast_buffers=False)
        budget = total_steps(self.steps_per_epoch, cfg)  # for the bar; epochs bound the loop, max_steps steps
        st.stopped_early = st.bad_rounds >= cfg.patience
        self.t_start, self.c_start = self.clock.wall(), self.clock.cpu()
        self.tick()  # a resumed run may have spent its budget already
        if self.is_main and cfg.progress:
            from tqdm import tqdm

            if self.budget_s is None:
                self.bar = tqdm(total=budget, initial=min(st.step, budget), unit="step", dynamic_ncols=True)
            else:  # a wall budget: the bar counts its seconds
                self.bar = tqdm(total=round(self.budget_s), initial=round(min(self.now_wall, self.budget_s)),
                                unit="s", dynamic_ncols=True)
        log.info("training %s: %d transitions, %d steps/epoch x %d epochs (budget %d steps, %s wall "
                 "minutes), %d ranks, device %s, bf16=%s, channels_last=%s, steps_per_call=%d, "
                 "unroll_steps=%d",
                 self.meta.name, len(cast(Sized, self.data.train)), self.steps_per_epoch, cfg.max_epochs,
                 budget, cfg.max_train_minutes, self.world, self.device, self.bf16, cfg.channels_last, self.k,
                 cfg.unroll_steps)

    def wall(self) -> float:
        """The run's wall seconds: earlier processes' (from last.pt) plus this one's since ``start``."""
        return self.state.wall_s + self.clock.wall() - self.t_start

    def cpu(self) -> float:
        """The run's CPU seconds (this process's ``process_time``), summed the same way."""
        return self.state.cpu_s + self.clock.cpu() - self.c_start

    def tick(self) -> bool:
        """Read the run's wall time into ``now_wall`` and return whether the wall budget is spent. Under DDP
        with a budget every rank takes rank 0's reading, so all take the same learning rate and stop at the
        same step."""
        wall = self.wall()
        if self.distributed and self.budget_s is not None:
            shared = torch.tensor([wall], dtype=torch.float64, device=self.device)
            dist.broadcast(shared, src=0)
            wall = float(shared)
        self.now_wall = wall
        self.state.budget_spent = self.budget_s is not None and wall >= self.budget_s
        return self.state.budget_spent

    def pair_batch(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``pairs_per_step`` random sweep pairs as (x, u, y) of 2P samples, the P first members then the P
        second ones (``pair_loss``). The draw is a function of (seed, step, rank): a resumed run repeats
        it."""
        assert self.pairs is not None
        rank = dist.get_rank() if self.distributed else 0
        rng = np.random.default_rng([self.cfg.seed, self.state.step, rank])
        picks = rng.integers(0, len(cast(Sized, self.pairs)), size=self.cfg.pairs_per_step)
        items = [self.pairs[int(i)] for i in picks]  # each (x (2, ...), u (2, ...), y (2, ...))
        return cast(tuple[torch.Tensor, torch.Tensor, torch.Tensor],
                    tuple(torch.cat([torch.stack([it[j][m] for it in items]) for m in (0, 1)])
                          for j in range(3)))

    def loss(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Training loss of one batch: one-step MSE (eq. training_loss), its pushforward or k-step form; with
        sweep pairs, 2P pair members join the batch and their difference term is added."""
        dev, mf, autocast, cfg = self.device, self.memory_format, self.autocast, self.cfg
        pairs = None
        if self.pairs is not None:
            xp, up, yp = self.pair_batch()
            x, u, y = torch.cat([x, xp]), torch.cat([u, up]), torch.cat([y, yp])
            pairs = PairTerms(cfg.pairs_per_step, cfg.pair_loss_weight, cfg.response_loss_weight,
                              self.meta.scene)
        x = x.to(dev, non_blocking=True).contiguous(memory_format=mf)  # (B, 2, D, H, W)
        if self.window == 1:
            y = y.to(dev, non_blocking=True).contiguous(memory_format=mf)
            u = u.to(dev, non_blocking=True)  # (B, 14)
            with autocast:
                pred = self.train_model(x, u).float()
            loss = torch.mean((pred - y) ** 2)
            if cfg.profile_loss_weight > 0:
                loss = loss + cfg.profile_loss_weight * profile_loss(pred, y, self.meta.scene)
            if pairs is not None:
                loss = loss + pairs.loss(pred, y)
            return loss
        if self.k == 1:  # u (B, U, 14), y (B, U, 2, D, H, W): pushforward over U transitions
            return pushforward_loss(self.train_model, x, u.to(dev), y.to(dev), autocast, mf,
                                    detach=not cfg.unroll_grad)
        # u (B, U·k, 14), y (B, U·k, 2, D, H, W): k-step targets over U calls
        return multistep_loss(self.train_model, x, u.to(dev), y.to(dev), self.k, autocast, mf,
                              self.step_weights, (cfg.profile_loss_weight, self.meta.scene), pairs,
                              detach=not cfg.unroll_grad)

    def train_epoch(self, epoch: int) -> dict[str, Any]:
        """One epoch (from the resumed batch on); returns its metrics.csv row without validation."""
        cfg, st, dev = self.cfg, self.state, self.device
        t_epoch = self.clock.wall()
        self.sampler.set_epoch(epoch)
        self.sampler.skip = st.skip * self.per_rank_batch  # batches trained before a mid-epoch resume
        self.train_model.train()
        loss_sum = torch.tensor(st.epoch_loss, dtype=torch.float64, device=dev)  # (Σ loss·n, n)
        st.epoch_loss = (0.0, 0.0)
        lr = cfg.lr
        for i, (x, u, y) in enumerate(self.loader, start=st.skip):
            if st.step >= self.step_cap:
                break
            lr = lr_at(st.step, self.steps_per_epoch, cfg, self.now_wall)
            for group in self.optimizer.param_groups:
                group["lr"] = lr
            loss = self.loss(x, u, y)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
            self.optimizer.step()
            if self.average is not None:
                self.average.update()
            st.step += 1
            loss_sum[0] += loss.detach().double() * x.shape[0]  # no host-device copy: the step is not
            loss_sum[1] += x.shape[0]  # synchronized with the device (the losses are read in ``losses``)
            self.pending.append(loss.detach())
            if len(self.pending) >= 4 * FINAL_LOSS_STEPS:  # read them now and then: the list stays short
                self.losses()
            spent = self.tick()
            if self.bar is not None and (st.step % BAR_EVERY == 0 or spent):
                done = st.step if self.budget_s is None else round(min(self.now_wall, self.budget_s))
                self.bar.update(done - self.bar.n)
                self.bar.set_postfix(epoch=epoch + 1, step=st.step, loss=f"{self.losses()[-1]:.3e}",
                                     lr=f"{lr:.2e}")
            if spent:  # the run ends here: validation and last.pt follow (``validation_due``, ``end_epoch``)
                break
            if (self.is_main and cfg.checkpoint_every and st.step % cfg.checkpoint_every == 0
                    and st.step < self.step_cap and (i + 1) < self.steps_per_epoch):
                self.save_last(epoch, loss_sum, batches=i + 1)
        st.skip = self.sampler.skip = 0
        self.losses()
        if self.distributed:
            dist.all_reduce(loss_sum)
        train_loss = float(loss_sum[0]) / max(float(loss_sum[1]), 1.0)
        return {"epoch": epoch + 1, "step": st.step, "lr": lr, "train_loss": train_loss,
                "epoch_seconds": self.clock.wall() - t_epoch, "wall_s": self.now_wall, "cpu_s": self.cpu(),
                "val_wall_s": st.val_wall_s}  # fmt: skip

    def losses(self) -> list[float]:
        """The last ``FINAL_LOSS_STEPS`` step losses (``RunState.recent_losses``), with the steps' losses
        still on the device read in one copy."""
        st = self.state
        if self.pending:
            st.recent_losses = (st.recent_losses + torch.stack(self.pending).tolist())[-FINAL_LOSS_STEPS:]
            self.pending.clear()
        return st.recent_losses

    def budget_done(self) -> bool:
        """Before an epoch: the wall budget is spent and the last epoch's weights were validated, so the run
        is over (validation, e.g., took the last of it). Spent with the last epoch unvalidated (its
        checkpoint took the last of it), the next step trips the budget inside the epoch and validates."""
        history = self.state.history
        return self.tick() and bool(history) and "val_avg_rmse" in history[-1]

    def validation_due(self, epoch: int) -> bool:
        """Every ``val_every`` epochs and at the end of the budget (epochs, steps or wall time)."""
        cfg = self.cfg
        end = epoch + 1 == cfg.max_epochs or self.state.step >= self.step_cap or self.state.budget_spent
        return (epoch + 1) % cfg.val_every == 0 or end

    def validate(self, epoch: int, row: dict[str, Any]) -> None:
        """Validation rollout: fills ``row``, updates best / patience, writes best.pt on improvement. With
        ``ema_decay`` the averaged weights are rolled out and written."""
        with nullcontext() if self.average is None else self.average.applied():
            self._validate(epoch, row)

    def _validate(self, epoch: int, row: dict[str, Any]) -> None:
        cfg, st, dev = self.cfg, self.state, self.device
        t_val = self.clock.wall()
        self.model.eval()
        sq: Any = None
        n = 0
        if self.val_index:  # streamed: one batch of trajectories in memory at a time
            sq, n = rollout_errors(self.model, (self.data.val[i] for i in self.val_index),
                                   steps=cfg.rollout_steps, batch_size=cfg.val_batch_size, device=dev)
        if self.distributed:  # ranks may hold no val case: share the length first
            length = torch.tensor([0 if sq is None else len(sq)], device=dev)
            dist.all_reduce(length, op=dist.ReduceOp.MAX)
            buf = torch.zeros(int(length) + 1, dtype=torch.float64, device=dev)
            if sq is not None:
                buf[:-1] = torch.as_tensor(sq, dtype=torch.float64)
            buf[-1] = n
            dist.all_reduce(buf)
            sq, n = buf[:-1].cpu().numpy(), int(buf[-1])
        if n == 0:
            raise ValueError("the validation split is empty; a validation rollout needs trajectories")
        val = rmse_summary(sq, n)
        seconds = self.clock.wall() - t_val
        st.val_wall_s += seconds
        row.update(val_avg_rmse=val["avg_rmse"], val_final_rmse=val["final_rmse"], val_mse=val["mse"],
                   val_seconds=seconds)
        score = val["avg_rmse"] if cfg.select_metric == "avg_rmse" else val["mse"]
        improved = score < st.best
        if improved:
            st.best, st.best_epoch, st.bad_rounds = score, epoch + 1, 0
        else:
            st.bad_rounds += 1
        st.stopped_early = st.bad_rounds >= cfg.patience
        log.info("epoch %d: train loss %.4e, val Avg RMSE %.5f, Final RMSE %.5f%s", epoch + 1,
                 row["train_loss"], val["avg_rmse"], val["final_rmse"],
                 " (best)" if improved else f" ({st.bad_rounds} w/o gain)")
        if improved and self.is_main:
            write_checkpoint_dict(self.best_path, self.checkpoint(st.history + [row], epoch + 1))

    def end_epoch(self, epoch: int, row: dict[str, Any]) -> None:
        """Record the epoch: history, last.pt and metrics.csv (rank 0), then sync the ranks."""
        self.state.history.append(row)
        if self.is_main:
            self.save_last(epoch + 1)
            _write_csv(self.out_dir / "metrics.csv", self.state.history)
        if self.distributed:
            dist.barrier()

    def save_last(self, epoch_done: int, partial: torch.Tensor | None = None, batches: int = 0) -> None:
        """last.pt with everything needed to resume (``RunState.train_state``)."""
        self.losses()
        ckpt = self.checkpoint(self.state.history, epoch_done)
        ckpt["train_state"] = self.state.train_state(self.optimizer, epoch_done, partial, batches,
                                                     wall_s=self.wall(), cpu_s=self.cpu())
        if self.average is not None:
            ckpt["train_state"]["ema"] = self.average.state_dict()
        write_checkpoint_dict(self.last_path, ckpt)

    def checkpoint(self, history: list[dict[str, Any]], epochs: int) -> dict[str, Any]:
        """A checkpoint of the current weights whose summary covers ``history`` (``epochs`` epochs)."""
        meta = self.meta
        return checkpoint_dict(self.model, model_name=meta.name, model_config=meta.config, scene=meta.scene,
                               rules=meta.rules, rules_perturbation=meta.rules_perturbation,
                               summary=self.summary(history, epochs), sim_config=meta.sim_config)

    def summary(self, history: list[dict[str, Any]] | None = None,
                epochs: int | None = None) -> dict[str, Any]:
        """The training summary (best.pt's ``summary``, ``summary.json``); default: the whole history so far.

        ``wall_s`` / ``cpu_s``: the run's time over every resume (training, validation, checkpoints), of
        which ``val_wall_s`` in validation; ``seconds``: this process's share. ``final_train_loss``: mean of
        the last ``final_loss_steps`` (<= FINAL_LOSS_STEPS) step losses (rank 0's batches under DDP); the
        last epoch's mean for a checkpoint written before step losses were kept.
        """
        st, cfg = self.state, self.cfg
        history = st.history if history is None else history
        recent = self.losses()
        final = sum(recent) / len(recent) if recent else (history[-1]["train_loss"] if history else None)
        return {
            "epochs": len(history) if epochs is None else epochs,
            "steps": st.step,
            "best_epoch": st.best_epoch,
            "best_val": st.best,
            "select_metric": cfg.select_metric,
            "stopped_early": st.stopped_early,
            "budget_minutes": cfg.max_train_minutes,
            "budget_spent": st.budget_spent,
            "wall_s": self.wall(),
            "cpu_s": self.cpu(),
            "val_wall_s": st.val_wall_s,
            "seconds": self.clock.wall() - self.t_start,
            "train_config": asdict(cfg),
            "final_train_loss": final,
            "final_loss_steps": len(recent),
            **self.meta.provenance,
        }


def train(
    cfg: TrainConfig,
    model: nn.Module,
    data: TrainData,
    out_dir: str | Path,
    meta: ModelMeta,
    *,
    resume: bool = False,
    clock: Clock | None = None,
) -> dict[str, Any]:
    """Train ``model`` on one-step transitions; returns the training summary (also in best.pt, summary.json).

    Args:
        cfg: hyper-parameters (TrainConfig).
        model: freshly built model (seeded by the caller); on resume its weights are replaced.
        data: TrainData (train transitions, validation trajectories).
        out_dir: where best.pt, last.pt and metrics.csv go.
        meta: model name/config/scene/rules stored in every checkpoint.
        resume: continue from out_dir/last.pt if present (else start fresh).
        clock: where wall and CPU time are read (default ``Clock()``: perf_counter, process_time).
    """
    cfg = cfg.resolved(pick_device(cfg.device).type)  # the device's batch, budgets in steps, scaled lr
    run = _Run(cfg, model, data, Path(out_dir), meta, clock or Clock())
    if resume:
        run.resume()
    run.start()
    st = run.state
    for epoch in range(st.epoch, cfg.max_epochs):
        if run.budget_done() or st.stopped_early or st.step >= run.step_cap:
            break
        row = run.train_epoch(epoch)
        if run.validation_due(epoch):
            run.validate(epoch, row)
        else:
            log.info("epoch %d: train loss %.4e (%.1f s)", epoch + 1, row["train_loss"], row["epoch_seconds"])
        run.end_epoch(epoch, row)
        if st.stopped_early:
            log.info("early stop: %d validation rounds without improvement", st.bad_rounds)
            break
    if run.bar is not None:
        run.bar.close()
    if st.budget_spent:
        log.info("wall budget of %s minutes spent at step %d", cfg.max_train_minutes, st.step)
    summary = run.summary()
    if run.is_main:
        tmp = run.out_dir / "summary.json.tmp"
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
        tmp.replace(run.out_dir / "summary.json")
    return summary
