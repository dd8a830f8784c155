"""The training loop ([supp_training], [supp_evaluation], eq. training_loss): one function, top to bottom.

One-step supervision (the paper): minimize the voxel-wise MSE between F_θ(x_t, u_t) and x_{t+1} on normalized
fields; with ``unroll_steps`` k > 1 the mean of k one-step MSEs along k consecutive transitions, each step fed
the previous detached prediction (``pushforward_loss``; not in the paper, see ``TrainConfig``). A model with
``steps_per_call`` k > 1 is trained on k-step targets: the (weighted) mean MSE of its k predicted states,
over ``unroll_steps`` calls chained by their detached last state (``multistep_loss``).

Every ``val_every`` epochs the model is rolled out autoregressively from x_0 over the full horizon on the
validation trajectories (no gradient); the best rollout is kept as ``best.pt`` and training stops after
``patience`` validation rounds without improvement. ``last.pt`` is written after every epoch (and every ``checkpoint_every`` steps inside one) with the optimizer, schedule step, RNG states,
history and the number of batches of the unfinished epoch, so a killed run resumes where it was saved and
reproduces the uninterrupted run (shuffling is a pure function of seed and epoch through
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
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

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
    state, total = x, 0.0
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
    state, total = x, 0.0
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
    batches still to train (the shuffled order itself is unchanged, so the remaining batches are identical)."""

    def __init__(self, base: DistributedSampler) -> None:
        self.base, self.skip = base, 0

    def set_epoch(self, epoch: int) -> None:
        self.base.set_epoch(epoch)

    def __iter__(self):
        return itertools.islice(iter(self.base), self.skip, None)

    def __len__(self) -> int:
        return len(self.base) - self.skip


def _write_csv(path: Path, history: list[dict[str, Any]]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        for row in history:
            w.writerow({k: row.get(k, "") for k in CSV_FIELDS})
    tmp.replace(path)


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
    out_dir = Path(out_dir)
    k = steps_per_call(model)
    window = cfg.unroll_steps * k  # transitions per training item
    if getattr(data.train, "unroll", 1) != window:
        raise ValueError(f"unroll_steps={cfg.unroll_steps} x steps_per_call={k} needs a train dataset of "
                         f"{window}-transition items; got unroll={getattr(data.train, 'unroll', 1)}")
    if cfg.step_loss_weights is not None and len(cfg.step_loss_weights) != k:
        raise ValueError(f"step_loss_weights has {len(cfg.step_loss_weights)} entries; the model predicts "
                         f"steps_per_call={k} states per call")
    distributed = dist.is_available() and dist.is_initialized()
    rank, world = (dist.get_rank(), dist.get_world_size()) if distributed else (0, 1)
    is_main = rank == 0
    if is_main:
        out_dir.mkdir(parents=True, exist_ok=True)

    # ---- device, precision, model --------------------------------------------------------------
    device = pick_device(cfg.device)
    memory_format = torch.channels_last_3d if cfg.channels_last else torch.contiguous_format
    model = model.to(device=device, memory_format=memory_format)
    autocast = (
        torch.autocast(device_type=device.type, dtype=torch.bfloat16) if cfg.bf16 else nullcontext()
    )
    optimizer = torch.optim.AdamW(
        model.parameters(), lr=cfg.lr, betas=cfg.betas, weight_decay=cfg.weight_decay
    )
    step_weights = None if cfg.step_loss_weights is None else torch.tensor(cfg.step_loss_weights)

    # ---- data: DistributedSampler also for one rank, so shuffling = f(seed, epoch) ----------------
    if cfg.batch_size % world:
        log.warning("batch_size %d is not divisible by world size %d", cfg.batch_size, world)
    per_rank_batch = max(1, cfg.batch_size // world)
    sampler = _ResumableSampler(
        DistributedSampler(data.train, num_replicas=world, rank=rank, shuffle=True, seed=cfg.seed))
    loader = DataLoader(
        data.train,
        batch_size=per_rank_batch,
        sampler=sampler,
        num_workers=cfg.num_workers,
        pin_memory=device.type == "cuda",
        persistent_workers=cfg.num_workers > 0,
    )
    steps_per_epoch = len(loader)
    val_index = list(range(rank, len(data.val), world))  # this rank's validation trajectories

    # ---- state, optionally resumed ---------------------------------------------------------------
    start_epoch, step, best, best_epoch, bad_rounds = 0, 0, math.inf, -1, 0
    epoch_loss = (0.0, 0.0)  # (Σ loss·n, n) of a partly trained epoch (mid-epoch last.pt)
    skip = 0  # batches of the resumed epoch already trained (mid-epoch last.pt)
    history: list[dict[str, Any]] = []
    last_path, best_path = out_dir / "last.pt", out_dir / "best.pt"
    if resume and last_path.is_file():
        ckpt = read_checkpoint(last_path)
        ts = ckpt["train_state"]
        unwrap(model).load_state_dict(ckpt["model_state"])
        optimizer.load_state_dict(ts["optimizer"])
        start_epoch, step = ts["epoch"], ts["schedule_step"]
        best, best_epoch, bad_rounds = ts["best"], ts["best_epoch"], ts["bad_rounds"]
        history = list(ts["history"])
        epoch_loss = tuple(ts.get("epoch_loss", (0.0, 0.0)))
        # count stored since mid-epoch checkpoints; epoch-end checkpoints resume at batch 0 even when the
        # steps per epoch change (e.g. a continuation with another unroll_steps)
        partly = epoch_loss[1] > 0  # only mid-epoch checkpoints carry the sums of an unfinished epoch
        skip = int(ts.get("epoch_batches", step - start_epoch * steps_per_epoch if partly else 0))
        _set_rng_state(ts["rng"])
        log.info("resumed from %s at epoch %d (best %.5g at epoch %d)", last_path, start_epoch, best, best_epoch)
    elif resume:
        log.info("--resume: no %s yet, starting fresh", last_path)
    train_model: nn.Module = model
    if distributed:
        ids = [device.index] if device.type == "cuda" else None
        # The compiled rule tensors are fixed buffers: nothing to broadcast after construction.
        train_model = nn.parallel.DistributedDataParallel(model, device_ids=ids, broadcast_buffers=False)

    budget = total_steps(steps_per_epoch, cfg)  # for the bar; epochs bound the loop, max_steps the steps
    step_cap = cfg.max_steps if cfg.max_steps is not None else math.inf
    stopped_early = bad_rounds >= cfg.patience
    t_start = time.perf_counter()
    bar = None
    if is_main and cfg.progress:
        from tqdm import tqdm

        bar = tqdm(total=budget, initial=min(step, budget), unit="step", dynamic_ncols=True)

    def save_last(epoch_done: int, partial: torch.Tensor | None = None, batches: int = 0) -> None:
        """last.pt with everything needed to resume; ``partial`` = loss sums of an unfinished epoch of which
        ``batches`` batches are trained."""
        train_state = {"optimizer": optimizer.state_dict(), "epoch": epoch_done, "schedule_step": step,
                       "best": best, "best_epoch": best_epoch, "bad_rounds": bad_rounds,
                       "history": history, "rng": _rng_state(),
                       "epoch_loss": (0.0, 0.0) if partial is None else tuple(float(v) for v in partial),
                       "epoch_batches": batches}
        ckpt = _ckpt(model, meta, cfg, history, best, best_epoch, epoch_done, t_start, stopped_early)
        ckpt["train_state"] = train_state
        write_checkpoint_dict(last_path, ckpt)
    log.info("training %s: %d transitions, %d steps/epoch x %d epochs (budget %d steps), %d ranks, device %s, "
             "bf16=%s, channels_last=%s, steps_per_call=%d, unroll_steps=%d", meta.name, len(data.train),
             steps_per_epoch, cfg.max_epochs, budget, world, device, cfg.bf16, cfg.channels_last, k,
             cfg.unroll_steps)

    epoch = start_epoch
    for epoch in range(start_epoch, cfg.max_epochs):
        if stopped_early or step >= step_cap:
            break
        # ---- one epoch of one-step MSE (eq. training_loss), or its pushforward form -----------------
        t_epoch = time.perf_counter()
        sampler.set_epoch(epoch)
        sampler.skip = skip * per_rank_batch  # batches of this epoch trained before a mid-epoch resume
        train_model.train()
        loss_sum = torch.tensor(epoch_loss, dtype=torch.float64, device=device)  # (Σ loss·n, n)
        epoch_loss = (0.0, 0.0)
        lr = cfg.lr
        for i, (x, u, y) in enumerate(loader, start=skip):
            if step >= step_cap:
                break
            lr = lr_at(step, steps_per_epoch, cfg)
            for group in optimizer.param_groups:
                group["lr"] = lr
            x = x.to(device, non_blocking=True).contiguous(memory_format=memory_format)  # (B, 2, D, H, W)
            if window == 1:
                y = y.to(device, non_blocking=True).contiguous(memory_format=memory_format)
                u = u.to(device, non_blocking=True)  # (B, 14)
                with autocast:
                    pred = train_model(x, u)
                loss = torch.mean((pred.float() - y) ** 2)
            elif k == 1:  # u (B, U, 14), y (B, U, 2, D, H, W): pushforward over U transitions
                loss = pushforward_loss(train_model, x, u.to(device), y.to(device), autocast, memory_format)
            else:  # u (B, U·k, 14), y (B, U·k, 2, D, H, W): k-step targets over U calls
                loss = multistep_loss(train_model, x, u.to(device), y.to(device), k, autocast, memory_format,
                                      step_weights)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            optimizer.step()
            step += 1
            loss_sum += torch.stack([loss.detach().double() * x.shape[0], torch.tensor(x.shape[0], device=device,
                                                                                       dtype=torch.float64)])
            if bar is not None:
                bar.update(1)
                bar.set_postfix(epoch=epoch + 1, loss=f"{loss.item():.3e}", lr=f"{lr:.2e}")
            if (is_main and cfg.checkpoint_every and step % cfg.checkpoint_every == 0
                    and step < step_cap and (i + 1) < steps_per_epoch):
                save_last(epoch, loss_sum, batches=i + 1)
        skip = sampler.skip = 0
        if distributed:
            dist.all_reduce(loss_sum)
        train_loss = float(loss_sum[0] / max(loss_sum[1], 1))
        row: dict[str, Any] = {"epoch": epoch + 1, "step": step, "lr": lr, "train_loss": train_loss,
                               "epoch_seconds": time.perf_counter() - t_epoch}

        # ---- validation rollout every val_every epochs and at the end of the budget ---------------
        if (epoch + 1) % cfg.val_every == 0 or epoch + 1 == cfg.max_epochs or step >= step_cap:
            t_val = time.perf_counter()
            model.eval()
            if val_index:  # streamed: one batch of trajectories in memory at a time
                sq, n = rollout_errors(model, (data.val[i] for i in val_index), steps=cfg.rollout_steps,
                                       batch_size=cfg.val_batch_size, device=device)
            else:
                sq, n = None, 0
            if distributed:  # ranks may hold no val case: share the length first
                length = torch.tensor([0 if sq is None else len(sq)], device=device)
                dist.all_reduce(length, op=dist.ReduceOp.MAX)
                buf = torch.zeros(int(length) + 1, dtype=torch.float64, device=device)
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
            improved = score < best
            if improved:
                best, best_epoch, bad_rounds = score, epoch + 1, 0
            else:
                bad_rounds += 1
            stopped_early = bad_rounds >= cfg.patience
            log.info("epoch %d: train loss %.4e, val Avg RMSE %.5f, Final RMSE %.5f%s", epoch + 1, train_loss,
                     val["avg_rmse"], val["final_rmse"], " (best)" if improved else f" ({bad_rounds} w/o gain)")
            if improved and is_main:
                write_checkpoint_dict(best_path, _ckpt(model, meta, cfg, history + [row], best, best_epoch,
                                                       epoch + 1, t_start, stopped_early))
        else:
            log.info("epoch %d: train loss %.4e (%.1f s)", epoch + 1, train_loss, row["epoch_seconds"])
        history.append(row)

        # ---- last.pt: everything needed to resume --------------------------------------------------
        if is_main:
            save_last(epoch + 1)
            _write_csv(out_dir / "metrics.csv", history)
        if distributed:
            dist.barrier()
        if stopped_early:
            log.info("early stop: %d validation rounds without improvement", bad_rounds)
            break
    if bar is not None:
        bar.close()
    return _summary(cfg, history, best, best_epoch, len(history), t_start, stopped_early)


def _summary(cfg: TrainConfig, history: list, best: float, best_epoch: int, epochs: int, t_start: float,
             stopped_early: bool) -> dict[str, Any]:
    return {
        "epochs": epochs,
        "best_epoch": best_epoch,
        "best_val": best,
        "select_metric": cfg.select_metric,
        "stopped_early": stopped_early,
        "seconds": time.perf_counter() - t_start,
        "train_config": asdict(cfg),
        "final_train_loss": history[-1]["train_loss"] if history else None,
    }


def _ckpt(model: nn.Module, meta: ModelMeta, cfg: TrainConfig, history: list, best: float, best_epoch: int,
          epoch: int, t_start: float, stopped_early: bool) -> dict[str, Any]:
    summary = _summary(cfg, history, best, best_epoch, epoch, t_start, stopped_early)
    return checkpoint_dict(model, model_name=meta.name, model_config=meta.config, scene=meta.scene,
                           rules=meta.rules, rules_perturbation=meta.rules_perturbation, summary=summary,
                           sim_config=meta.sim_config)
