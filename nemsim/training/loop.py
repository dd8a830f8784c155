"""The training loop ([supp_training], [supp_evaluation], eq. training_loss): one function, top to bottom.

One-step supervision (the paper): minimize the voxel-wise MSE between F_θ(x_t, u_t) and x_{t+1} on normalized
fields; with ``unroll_steps`` k > 1 the mean of k one-step MSEs along k consecutive transitions, each step fed
the previous detached prediction (``pushforward_loss``; not in the paper, see ``TrainConfig``). A model with
``steps_per_call`` k > 1 is trained on k-step targets: the (weighted) mean MSE of its k predicted states,
over ``unroll_steps`` calls chained by their detached last state (``multistep_loss``).

Every ``val_every`` epochs the model is rolled out autoregressively from x_0 over the full horizon on the
validation trajectories (no gradient); the best rollout is kept as ``best.pt`` and training stops after
``patience`` validation rounds without improvement. ``last.pt`` is written after every epoch (and every
``checkpoint_every`` steps inside one) with the optimizer, schedule step, RNG states, history and the number
of batches of the unfinished epoch (``RunState``), so a killed run resumes where it was saved and reproduces
the uninterrupted run (shuffling is a pure function of seed and epoch through
``DistributedSampler.set_epoch``; the resumed epoch skips the batches already trained). ``max_steps`` ends a
run inside an epoch, with a validation rollout there.

DDP: if ``torch.distributed`` is initialized (``torchrun``, see ``nemsim.train``) the model is wrapped
in DistributedDataParallel, each rank sees a disjoint shard of every epoch (per-rank batch =
batch_size / world size, so the global batch stays 24), validation trajectories are sharded and their
error sums all-reduced; only rank 0 writes files.

Outputs in ``out_dir``: ``best.pt``, ``last.pt``, ``metrics.csv`` (one row per epoch: lr, train loss,
validation metrics when computed, seconds). The log file and the progress bar are set up by the
entry point / here on rank 0 only.
"""

from __future__ import annotations

import csv
import itertools
import logging
import math
import random
import time
from collections.abc import Sized
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

from nemsim.checkpoint import checkpoint_dict, read_checkpoint, unwrap, write_checkpoint_dict
from nemsim.evaluation.evaluate import rmse_summary, rollout_errors
from nemsim.evaluation.rollout import steps_per_call
from nemsim.scenes import Scene
from nemsim.training.config import TrainConfig

log = logging.getLogger(__name__)

CSV_FIELDS = ("epoch", "step", "lr", "train_loss", "val_avg_rmse", "val_final_rmse", "val_mse",
              "epoch_seconds", "val_seconds")


@dataclass
class TrainData:
    """train: items (x_t (2,D,H,W), u_t (14,), x_{t+1}); val: indexable of (case_id, states, u)."""

    train: Dataset
    val: Any


@dataclass
class ModelMeta:
    """What a checkpoint needs to rebuild the model (see nemsim.checkpoint)."""

    name: str
    config: dict[str, Any]
    scene: Scene
    rules: Any  # RuleTensors
    rules_perturbation: dict[str, Any] | None = None
    sim_config: dict[str, Any] | None = None  # the data file's simulator configuration (``generator``)


def total_steps(steps_per_epoch: int, cfg: TrainConfig) -> int:
    """The run's optimizer-step budget: max_epochs epochs, or max_steps if that is smaller."""
    total = cfg.max_epochs * steps_per_epoch
    return total if cfg.max_steps is None else min(total, cfg.max_steps)


def lr_at(step: int, steps_per_epoch: int, cfg: TrainConfig) -> float:
    """Linear warm-up (``warmup_steps``, else ``warmup_epochs``) then half-cosine from lr to min_lr at the
    end of the budget (``total_steps``)."""
    warm = cfg.warmup_steps if cfg.warmup_steps is not None else cfg.warmup_epochs * steps_per_epoch
    total = max(total_steps(steps_per_epoch, cfg), warm + 1)
    if step < warm:
        return cfg.lr * (step + 1) / warm
    progress = min((step - warm) / max(total - warm, 1), 1.0)
    return cfg.min_lr + 0.5 * (cfg.lr - cfg.min_lr) * (1.0 + math.cos(math.pi * progress))


def pushforward_loss(model: nn.Module, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor, autocast,
                     memory_format=torch.contiguous_format) -> torch.Tensor:
    """Mean of k one-step MSEs along a k-transition window, each step fed the previous detached prediction.

    x (B, 2, D, H, W) = x_t; u (B, k, 14); y (B, k, 2, D, H, W) = x_{t+1..t+k}. Gradients flow only
    through each single step (no backpropagation through time): cost and memory are those of k steps.
    """
    k = u.shape[1]
    state, total = x, cast(Any, 0.0)  # a tensor after the first step
    for j in range(k):
        with autocast:
            pred = model(state.contiguous(memory_format=memory_format), u[:, j])
        pred = pred.float()
        total = total + torch.mean((pred - y[:, j]) ** 2)
        state = pred.detach()
    return total / k


def multistep_loss(model: nn.Module, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor, k: int, autocast,
                   memory_format=torch.contiguous_format,
                   weights: torch.Tensor | None = None) -> torch.Tensor:
    """Loss of a model predicting k states per call, over U = u.shape[1] / k calls chained by their detached
    last state (the pushforward term over calls of k; U = 1: plain k-step supervision).

    x (B, 2, D, H, W) = x_t; u (B, U·k, 14); y (B, U·k, 2, D, H, W) = x_{t+1..t+Uk}; weights (k,) per
    predicted state (None = uniform), normalized to sum 1. Call c predicts x_{t+ck+1..t+ck+k} under the
    controls of its first transition u_{t+ck} (as the rollout does with constant controls). Returns the mean
    over calls of Σ_j w_j MSE_j. With k = 1 this is ``pushforward_loss`` (model called as model(x, u)).
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
        state = pred[:, -1].detach()
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
                   epoch_loss=(float(epoch_loss[0]), float(epoch_loss[1])), skip=skip)  # fmt: skip

    def train_state(self, optimizer: torch.optim.Optimizer, epoch_done: int, partial: torch.Tensor | None,
                    batches: int) -> dict[str, Any]:
        """``last.pt``'s ``train_state``: ``partial`` = loss sums of an unfinished epoch of which ``batches``
        batches are trained (None at an epoch's end)."""
        return {"optimizer": optimizer.state_dict(), "epoch": epoch_done, "schedule_step": self.step,
                "best": self.best, "best_epoch": self.best_epoch, "bad_rounds": self.bad_rounds,
                "history": self.history, "rng": _rng_state(),
                "epoch_loss": (0.0, 0.0) if partial is None else tuple(float(v) for v in partial),
                "epoch_batches": batches}  # fmt: skip


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
    loader = DataLoader(
        train_set,
        batch_size=per_rank_batch,
        sampler=sampler,
        num_workers=cfg.num_workers,
        pin_memory=device.type == "cuda",
        persistent_workers=cfg.num_workers > 0,
    )
    return loader, sampler, per_rank_batch


class _Run:
    """One training run: the fixed pieces (model, optimizer, loader, precision) and the ``RunState``."""

    def __init__(self, cfg: TrainConfig, model: nn.Module, data: TrainData, out_dir: Path,
                 meta: ModelMeta) -> None:
        self.cfg, self.data, self.out_dir, self.meta = cfg, data, out_dir, meta
        self.k = steps_per_call(model)
        self.window = _check_items(cfg, data, self.k)
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
        self.autocast = (
            torch.autocast(device_type=self.device.type, dtype=torch.bfloat16) if cfg.bf16 else nullcontext()
        )
        self.optimizer = torch.optim.AdamW(
            self.model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay
        )
        self.step_weights = None if cfg.step_loss_weights is None else torch.tensor(cfg.step_loss_weights)
        # ---- data --------------------------------------------------------------------------------------
        self.loader, self.sampler, self.per_rank_batch = _train_loader(data.train, cfg, rank, world,
                                                                       self.device)
        self.steps_per_epoch = len(self.loader)
        self.val_index = list(range(rank, len(data.val), world))  # this rank's validation trajectories
        self.world = world
        self.state = RunState()
        self.step_cap = cfg.max_steps if cfg.max_steps is not None else math.inf
        self.last_path, self.best_path = out_dir / "last.pt", out_dir / "best.pt"
        self.t_start = time.perf_counter()
        self.bar: Any = None

    def resume(self) -> None:
        """Continue from ``last.pt`` if there is one: weights, optimizer, state, RNG streams."""
        if not self.last_path.is_file():
            log.info("--resume: no %s yet, starting fresh", self.last_path)
            return
        ckpt = read_checkpoint(self.last_path)
        ts = ckpt["train_state"]
        unwrap(self.model).load_state_dict(ckpt["model_state"])
        self.optimizer.load_state_dict(ts["optimizer"])
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
        self.t_start = time.perf_counter()
        if self.is_main and cfg.progress:
            from tqdm import tqdm

            self.bar = tqdm(total=budget, initial=min(st.step, budget), unit="step", dynamic_ncols=True)
        log.info("training %s: %d transitions, %d steps/epoch x %d epochs (budget %d steps), %d ranks, "
                 "device %s, bf16=%s, channels_last=%s, steps_per_call=%d, unroll_steps=%d", self.meta.name,
                 len(cast(Sized, self.data.train)), self.steps_per_epoch, cfg.max_epochs, budget, self.world,
                 self.device, cfg.bf16, cfg.channels_last, self.k, cfg.unroll_steps)

    def loss(self, x: torch.Tensor, u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Training loss of one batch: one-step MSE (eq. training_loss), its pushforward or k-step form."""
        dev, mf, autocast = self.device, self.memory_format, self.autocast
        x = x.to(dev, non_blocking=True).contiguous(memory_format=mf)  # (B, 2, D, H, W)
        if self.window == 1:
            y = y.to(dev, non_blocking=True).contiguous(memory_format=mf)
            u = u.to(dev, non_blocking=True)  # (B, 14)
            with autocast:
                pred = self.train_model(x, u)
            return torch.mean((pred.float() - y) ** 2)
        if self.k == 1:  # u (B, U, 14), y (B, U, 2, D, H, W): pushforward over U transitions
            return pushforward_loss(self.train_model, x, u.to(dev), y.to(dev), autocast, mf)
        # u (B, U·k, 14), y (B, U·k, 2, D, H, W): k-step targets over U calls
        return multistep_loss(self.train_model, x, u.to(dev), y.to(dev), self.k, autocast, mf,
                              self.step_weights)

    def train_epoch(self, epoch: int) -> dict[str, Any]:
        """One epoch (from the resumed batch on); returns its metrics.csv row without validation."""
        cfg, st, dev = self.cfg, self.state, self.device
        t_epoch = time.perf_counter()
        self.sampler.set_epoch(epoch)
        self.sampler.skip = st.skip * self.per_rank_batch  # batches trained before a mid-epoch resume
        self.train_model.train()
        loss_sum = torch.tensor(st.epoch_loss, dtype=torch.float64, device=dev)  # (Σ loss·n, n)
        st.epoch_loss = (0.0, 0.0)
        lr = cfg.lr
        for i, (x, u, y) in enumerate(self.loader, start=st.skip):
            if st.step >= self.step_cap:
                break
            lr = lr_at(st.step, self.steps_per_epoch, cfg)
            for group in self.optimizer.param_groups:
                group["lr"] = lr
            loss = self.loss(x, u, y)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), cfg.grad_clip)
            self.optimizer.step()
            st.step += 1
            n = torch.tensor(x.shape[0], device=dev, dtype=torch.float64)
            loss_sum += torch.stack([loss.detach().double() * x.shape[0], n])
            if self.bar is not None:
                self.bar.update(1)
                self.bar.set_postfix(epoch=epoch + 1, loss=f"{loss.item():.3e}", lr=f"{lr:.2e}")
            if (self.is_main and cfg.checkpoint_every and st.step % cfg.checkpoint_every == 0
                    and st.step < self.step_cap and (i + 1) < self.steps_per_epoch):
                self.save_last(epoch, loss_sum, batches=i + 1)
        st.skip = self.sampler.skip = 0
        if self.distributed:
            dist.all_reduce(loss_sum)
        train_loss = float(loss_sum[0]) / max(float(loss_sum[1]), 1.0)
        return {"epoch": epoch + 1, "step": st.step, "lr": lr, "train_loss": train_loss,
                "epoch_seconds": time.perf_counter() - t_epoch}  # fmt: skip

    def validation_due(self, epoch: int) -> bool:
        """Every ``val_every`` epochs and at the end of the budget."""
        cfg = self.cfg
        end = epoch + 1 == cfg.max_epochs or self.state.step >= self.step_cap
        return (epoch + 1) % cfg.val_every == 0 or end

    def validate(self, epoch: int, row: dict[str, Any]) -> None:
        """Validation rollout: fills ``row``, updates best / patience, writes best.pt on improvement."""
        cfg, st, dev = self.cfg, self.state, self.device
        t_val = time.perf_counter()
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
        row.update(val_avg_rmse=val["avg_rmse"], val_final_rmse=val["final_rmse"], val_mse=val["mse"],
                   val_seconds=time.perf_counter() - t_val)
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
        ckpt = self.checkpoint(self.state.history, epoch_done)
        ckpt["train_state"] = self.state.train_state(self.optimizer, epoch_done, partial, batches)
        write_checkpoint_dict(self.last_path, ckpt)

    def checkpoint(self, history: list[dict[str, Any]], epochs: int) -> dict[str, Any]:
        """A checkpoint of the current weights whose summary covers ``history`` (``epochs`` epochs)."""
        meta = self.meta
        return checkpoint_dict(self.model, model_name=meta.name, model_config=meta.config, scene=meta.scene,
                               rules=meta.rules, rules_perturbation=meta.rules_perturbation,
                               summary=self.summary(history, epochs), sim_config=meta.sim_config)

    def summary(self, history: list[dict[str, Any]] | None = None,
                epochs: int | None = None) -> dict[str, Any]:
        """The training summary (best.pt's ``summary``); default: the whole history so far."""
        st, cfg = self.state, self.cfg
        history = st.history if history is None else history
        return {
            "epochs": len(history) if epochs is None else epochs,
            "best_epoch": st.best_epoch,
            "best_val": st.best,
            "select_metric": cfg.select_metric,
            "stopped_early": st.stopped_early,
            "seconds": time.perf_counter() - self.t_start,
            "train_config": asdict(cfg),
            "final_train_loss": history[-1]["train_loss"] if history else None,
        }


def train(
    cfg: TrainConfig,
    model: nn.Module,
    data: TrainData,
    out_dir: str | Path,
    meta: ModelMeta,
    *,
    resume: bool = False,
) -> dict[str, Any]:
    """Train ``model`` on one-step transitions; returns the training summary (also stored in best.pt).

    Args:
        cfg: hyper-parameters (TrainConfig).
        model: freshly built model (seeded by the caller); on resume its weights are replaced.
        data: TrainData (train transitions, validation trajectories).
        out_dir: where best.pt, last.pt and metrics.csv go.
        meta: model name/config/scene/rules stored in every checkpoint.
        resume: continue from out_dir/last.pt if present (else start fresh).
    """
    run = _Run(cfg, model, data, Path(out_dir), meta)
    if resume:
        run.resume()
    run.start()
    st = run.state
    for epoch in range(st.epoch, cfg.max_epochs):
        if st.stopped_early or st.step >= run.step_cap:
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
    return run.summary()
