"""Training configuration: every hyper-parameter of [supp_training] and [supp_evaluation] is a field.

Paper values ([supp_training]): AdamW, lr 5e-4, weight decay 1e-5, 10-epoch linear warm-up, cosine
annealing to 1e-5, gradient-norm clip 1.0, batch 24, at most 350 epochs, seed 0, validation every 10 epochs
with a full 100-step autoregressive rollout ([supp_evaluation]), early stopping after 20 validation rounds
without improvement. Where the paper is silent: AdamW's default betas; the learning rate is set every
optimizer step; the best checkpoint has the lowest validation Avg RMSE (eq:supp_avg_rmse;
``select_metric="mse"`` for the paper's "mean validation-rollout MSE").

The loss of a sample of U network calls with k predicted states each (the paper: U = k = 1,
eq:training_loss; the extra terms are 0 by default):

    L = mean_c sum_j w_j MSE(x̂_cj, x_cj)  +  λ_p MSE(m(x̂), m(x))  +  λ_pair MSE(x̂_b - x̂_a, x_b - x_a)
        +  λ_resp MSE(m(x̂_b) - m(x̂_a), m(x_b) - m(x_a))

  * ``unroll_steps`` U: call c starts from call c-1's prediction, detached (the pushforward trick of
    Brandstetter, Worrall & Welling 2022) unless ``unroll_grad``; it trains the model on the states its own
    rollout visits, where one-step training drifts. ``step_loss_weights`` w_j (default uniform).
  * ``profile_loss_weight`` λ_p: m = the differentiable profile metrics (``nemsim.geometry.soft_profile``,
    voxels) of each call's last predicted state, a trench's at its own Si top (``training.loop``). The
    field MSE weighs a one-voxel width error at the hole's bottom like noise in a few voxels.
  * ``pair_loss_weight`` λ_pair: ``pairs_per_step`` sweep pairs (``nemsim.data.dataset.PairDataset``: two
    recipes that differ in one control group, one seed) join every batch. A Latin hypercube moves every
    control at once, so a single case weighs a control's response no more than the Monte Carlo noise;
    a pair's difference isolates it. docs/experiments.md compares these terms.
  * ``response_loss_weight`` λ_resp: the same pairs' difference read as profile metrics (the response a
    process engineer reads, in voxels, ``PROFILE_LOSS_METRICS``). The field difference of a one-group move
    is a thin band of sub-voxel changes along the surface, which the field MSE weighs like noise; the
    metric difference is the response itself. Simulated with common random numbers (``nemsim generate
    --sim-rng counter``), the pair's difference carries 22–37 % less noise than two independent runs
    (benchmarks/small/pair_noise).
  * ``ema_decay``: validate and keep a moving average of the weights (``nemsim.training.average``).

Budgets: ``max_epochs``, ``max_steps`` or ``max_train_minutes`` (wall clock of steps, validation and
checkpoint writes, summed over ``--resume``: the equal-time comparison of models of different speed; the
cosine then spans the budget, so every model reaches ``min_lr`` when its time runs out, and a resumed run
is not bit-identical). ``checkpoint_every`` writes last.pt inside an epoch. ``bf16`` (training forward only)
and ``channels_last``: defaults from benchmarks/small/README.md.

One recipe on any device (``resolved``): the budgets can be given in training items seen (``max_samples``,
``warmup_samples``, ``samples_per_epoch``), which become steps at the batch the run takes, so a recipe trains
the same amount whatever its batch. ``cuda`` holds the values that change on a CUDA device (the batch that
fills it, the validation batch); ``lr_scaling`` moves the learning rate with the batch from the one it was
tuned at (``base_batch_size``): ``sqrt`` is the square-root rule of adaptive optimizers (Malladi, Lyu,
Panigrahi & Arora 2022, "On the SDEs and scaling rules for adaptive gradient algorithms"): Adam's update
noise at batch B and lr η matches that at κB and √κ η. ``min_lr`` scales with it (the cosine keeps its
shape).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Literal

# The faster setting of one NEMSim training step on the small scene: channels_last_3d off, bf16 autocast on
# where the hardware computes in bfloat16 (benchmarks/small/README.md, "Training-step precision and memory
# format"; ``nemsim.inference.precision.native_bf16``).
DEFAULT_CHANNELS_LAST = False
DEFAULT_BF16 = None  # None: ``native_bf16`` of the training device
LR_SCALING = {"none": 0.0, "sqrt": 0.5, "linear": 1.0}  # lr_scaling -> exponent p of (batch / base)^p
# what ``TrainConfig.cuda`` may change: the batch that fills the device and what goes with it
DEVICE_FIELDS = ("batch_size", "val_batch_size", "lr", "checkpoint_every", "num_workers", "bf16")


@dataclass(frozen=True)
class TrainConfig:
    # --- optimizer ([supp_training]) ---
    lr: float = 5e-4  # AdamW initial (peak) learning rate
    weight_decay: float = 1e-5  # AdamW decoupled weight decay
    betas: tuple[float, float] = (0.9, 0.999)  # paper silent: AdamW defaults
    warmup_epochs: int = 10  # linear warm-up length, epochs
    min_lr: float = 1e-5  # cosine annealing floor
    grad_clip: float = 1.0  # max global gradient norm
    batch_size: int = 24  # transitions per optimizer step (global, split over DDP ranks)
    unroll_steps: int = 1  # network calls per sample: 1 = the paper's loss; U > 1 adds U-1 pushforward calls
    unroll_grad: bool = False  # U > 1: backpropagate through the chained calls instead of detaching them
    step_loss_weights: tuple[float, ...] | None = None  # k-step models: weight of each predicted state's MSE
    profile_loss_weight: float = 0.0  # lambda of the profile-metric term (0 = the paper's loss; docstring)
    ema_decay: float = 0.0  # validate and keep a moving average of the weights (0 = off; docstring)
    pair_loss_weight: float = 0.0  # lambda of the sweep-pair difference term (needs --pair-data; docstring)
    response_loss_weight: float = 0.0  # lambda of the sweep pairs' profile-metric response term (docstring)
    pairs_per_step: int = 4  # sweep pairs added to every batch when training with --pair-data
    max_epochs: int = 350  # epoch budget; the cosine spans warm-up end .. max_epochs
    max_steps: int | None = None  # optimizer-step budget; if set, training ends there and the cosine spans it
    max_train_minutes: float | None = None  # wall-clock budget (training + validation, summed over resumes);
    # if set, training ends when it is spent and the cosine spans it (instead of max_steps / max_epochs)
    warmup_steps: int | None = None  # warm-up length in steps; overrides warmup_epochs when set
    checkpoint_every: int | None = None  # also write last.pt every N steps (mid-epoch resume); None: epochs
    batches_per_epoch: int | None = None  # end each epoch after N batches (a random sample of the shuffled
    # training set): a large data set still validates, and keeps best.pt, every N steps; None = all of it
    # --- budgets in items seen, the same on every device (``resolved`` turns them into steps) ---
    max_samples: int | None = None  # items budget: ceil(max_samples / batch_size) steps (max_steps if less)
    warmup_samples: int | None = None  # warm-up in items: warmup_steps = ceil(warmup_samples / batch_size)
    samples_per_epoch: int | None = None  # items per epoch: batches_per_epoch = ceil(. / batch_size)
    # --- the batch that fills the device, and the learning rate that goes with it ---
    lr_scaling: Literal["none", "sqrt", "linear"] = "none"  # lr (and min_lr) x (batch / base_batch_size)^p
    base_batch_size: int | None = None  # the batch lr was tuned at (None: batch_size, nothing scales)
    cuda: dict[str, Any] | None = None  # fields that change on a CUDA device, e.g. {batch_size: 256}
    # --- validation / model selection ([supp_evaluation]) ---
    val_every: int = 10  # epochs between validation rollouts
    patience: int = 20  # validation rounds without improvement before early stop
    rollout_steps: int | None = None  # None = scene horizon (100 transitions)
    val_batch_size: int = 8  # trajectories rolled out together during validation
    val_cases: int | None = None  # validate on the first N validation trajectories only (None = all)
    test_cases: int | None = None  # final test of best.pt on the first N test trajectories (None = all)
    select_metric: Literal["avg_rmse", "mse"] = "avg_rmse"
    # --- reproducibility / data ---
    seed: int = 0
    num_workers: int = 0  # DataLoader workers per rank
    # average every training state over the scene's symmetries (nemsim.symmetry): quieter targets
    symmetrize_targets: bool = False
    # decode the training set once and hold it in memory (float16; on the GPU when it fits): MemoryTransitions
    in_memory: bool = False
    # --- precision and device ---
    channels_last: bool = DEFAULT_CHANNELS_LAST  # torch.channels_last_3d for model and inputs
    bf16: bool | None = DEFAULT_BF16  # bfloat16 autocast for the training forward pass (rollouts stay fp32);
    # None: where the device computes in bfloat16 (``native_bf16``)
    device: str = "auto"  # "auto" (cuda if available else cpu), "cpu", "cuda", "cuda:1", ...
    # --- bookkeeping ---
    progress: bool = True  # tqdm bar with loss and ETA (rank 0 only)

    def __post_init__(self) -> None:
        if self.lr <= 0 or self.min_lr < 0 or self.min_lr > self.lr:
            raise ValueError(f"need 0 <= min_lr ({self.min_lr}) <= lr ({self.lr}) and lr > 0")
        for name in ("batch_size", "unroll_steps", "max_epochs", "val_every", "patience", "val_batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        for name in ("max_steps", "warmup_steps", "checkpoint_every", "batches_per_epoch", "val_cases",
                     "test_cases"):
            value = getattr(self, name)
            low = 0 if name == "warmup_steps" else 1
            if value is not None and value < low:
                raise ValueError(f"{name} must be None or >= {low}, got {value}")
        if self.max_train_minutes is not None and not self.max_train_minutes > 0:
            raise ValueError(f"max_train_minutes must be None or > 0, got {self.max_train_minutes}")
        if self.warmup_epochs < 0:
            raise ValueError(f"warmup_epochs must be >= 0, got {self.warmup_epochs}")
        if self.rollout_steps is not None and self.rollout_steps < 1:
            raise ValueError(f"rollout_steps must be >= 1 or None, got {self.rollout_steps}")
        w = self.step_loss_weights
        if w is not None and (len(w) == 0 or min(w) < 0 or sum(w) <= 0):
            raise ValueError(f"step_loss_weights must be None or non-negative with a positive sum, one per "
                             f"predicted state; got {w}")
        if not self.profile_loss_weight >= 0:
            raise ValueError(f"profile_loss_weight must be >= 0, got {self.profile_loss_weight}")
        if not self.pair_loss_weight >= 0:
            raise ValueError(f"pair_loss_weight must be >= 0, got {self.pair_loss_weight}")
        if not self.response_loss_weight >= 0:
            raise ValueError(f"response_loss_weight must be >= 0, got {self.response_loss_weight}")
        if self.pairs_per_step < 1:
            raise ValueError(f"pairs_per_step must be >= 1, got {self.pairs_per_step}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in [0, 1) (0 = off), got {self.ema_decay}")
        if self.select_metric not in ("avg_rmse", "mse"):
            raise ValueError(f"select_metric={self.select_metric!r}; expected one of ['avg_rmse', 'mse']")
        for name in ("max_samples", "samples_per_epoch", "base_batch_size"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be None or >= 1, got {value}")
        if self.warmup_samples is not None and self.warmup_samples < 0:
            raise ValueError(f"warmup_samples must be None or >= 0, got {self.warmup_samples}")
        if self.lr_scaling not in LR_SCALING:
            raise ValueError(f"lr_scaling={self.lr_scaling!r}; expected one of {sorted(LR_SCALING)}")
        if self.cuda is not None and (not isinstance(self.cuda, dict) or set(self.cuda) - set(DEVICE_FIELDS)):
            raise ValueError(f"cuda: a mapping of some of {list(DEVICE_FIELDS)}, got {self.cuda!r}")

    def resolved(self, device_type: str) -> "TrainConfig":
        """The config a run on ``device_type`` ("cpu", "cuda") takes: the ``cuda`` overrides on a CUDA
        device, the budgets in items turned into steps at its batch, the learning rate scaled by
        ``lr_scaling`` from ``base_batch_size``. The result resolves to itself (its ``cuda`` is applied and
        cleared, its learning rate rule spent), so a resumed run gets the same numbers."""
        on_cuda = device_type == "cuda"
        cfg = self.replace(**(self.cuda or {}), cuda=None) if on_cuda else self.replace(cuda=None)
        b = cfg.batch_size
        steps = {name: -(-value // b) for name, value in (("max_steps", cfg.max_samples),
                                                           ("warmup_steps", cfg.warmup_samples),
                                                           ("batches_per_epoch", cfg.samples_per_epoch))
                 if value is not None}  # fmt: skip
        if cfg.max_steps is not None and "max_steps" in steps:  # both budgets: whichever ends first
            steps["max_steps"] = min(steps["max_steps"], cfg.max_steps)
        factor = (b / (cfg.base_batch_size or b)) ** LR_SCALING[cfg.lr_scaling]
        return cfg.replace(**steps, lr=cfg.lr * factor, min_lr=cfg.min_lr * factor, lr_scaling="none",
                           base_batch_size=None)

    def replace(self, **changes: Any) -> "TrainConfig":
        return from_dict({**asdict(self), **changes})


def from_dict(values: dict[str, Any]) -> TrainConfig:
    """Build a TrainConfig from plain values (a config file, a checkpoint); unknown keys are an error."""
    known = {f.name for f in fields(TrainConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown training config keys {unknown}; expected some of {sorted(known)}")
    values = dict(values)
    for f in fields(TrainConfig):  # YAML 1.1 reads 1e-4 (no dot) as a string
        if f.type in ("float", "float | None") and isinstance(values.get(f.name), str):
            try:
                values[f.name] = float(values[f.name])
            except ValueError:
                raise ValueError(f"{f.name} must be a number, got {values[f.name]!r}") from None
    if "betas" in values:
        values["betas"] = tuple(values["betas"])
    if values.get("step_loss_weights") is not None:
        values["step_loss_weights"] = tuple(float(w) for w in values["step_loss_weights"])
    return TrainConfig(**values)


def read_config_file(path: str | Path) -> tuple[TrainConfig, dict[str, Any]]:
    """Read a YAML or JSON file: TrainConfig keys at the top level, model overrides under ``model:``.

    Returns (train_config, model_overrides). Called by entry points only (library code reads no files).
    """
    import yaml  # JSON is a subset of YAML

    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a YAML or JSON text file ({exc})") from None
    raw = yaml.safe_load(text) or {}
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a mapping of config keys, got {type(raw).__name__}")
    model_overrides = raw.pop("model", None) or {}
    if not isinstance(model_overrides, dict):
        raise ValueError(f"{path}: 'model' must be a mapping of model config overrides")
    return from_dict(raw), model_overrides


def to_json(cfg: TrainConfig) -> str:
    return json.dumps(asdict(cfg), sort_keys=True)
