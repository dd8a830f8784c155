"""Training configuration: every hyper-parameter of [supp_training] and [supp_evaluation] is a field.

Paper values ([supp_training]): AdamW, lr 5e-4, weight decay 1e-5, 10-epoch linear warm-up, cosine
annealing to 1e-5, gradient-norm clip 1.0, batch 24, at most 350 epochs, seed 0, validation every
10 epochs with a full 100-step autoregressive rollout ([supp_evaluation]), early stopping after 20
validation rounds without improvement.

Choices where the paper is silent (each a field, so a config file can change it):
  * ``betas`` keep the AdamW defaults (0.9, 0.999).
  * the learning rate is set every optimizer step (not every epoch): linear from lr/warmup_steps to lr
    over the first ``warmup_epochs`` epochs, then half-cosine down to ``min_lr`` at ``max_epochs``.
  * best checkpoint = lowest validation-rollout Avg RMSE (eq. supp_avg_rmse); [supp_evaluation] says
    "mean validation-rollout MSE" -- ``select_metric`` switches to "mse" (mean over steps of MSE_t).
  * ``max_steps`` is a budget in optimizer steps for runs shorter than one epoch (the baselines' equal-budget
    comparison on this CPU, where one of their epochs takes hours); ``checkpoint_every`` writes last.pt
    inside an epoch so such a run resumes where it stopped (the shuffled order is a function of seed and
    epoch, so the resumed run skips the batches already seen). ``val_cases``/``test_cases`` take the first
    N trajectories of the split (manifest order) when a full 100-trajectory rollout costs too much.
  * ``unroll_steps`` (not in the paper, default 1 = the paper's eq. training_loss): with k > 1 each sample is
    k consecutive transitions; the model steps from its own detached prediction (the "pushforward trick" of
    Brandstetter, Worrall & Welling 2022) and the loss is the mean of the k one-step MSEs. Trained one-step
    only, NEMSim drifts past the trained horizon (``nemsim stress``); the pushforward term trains it on the
    states its own rollout visits, at ~k times the cost of a step.
  * multi-step models (``model: {steps_per_call: k}``, not in the paper): each network call predicts k states,
    and the loss is the mean over the k predicted states of their MSE against x_{t+1..t+k} (weighted by
    ``step_loss_weights`` if given, normalized to sum 1). ``unroll_steps`` counts network calls: with U > 1 a
    sample is U·k consecutive transitions and call c starts from the detached k-th state of call c-1 (the
    pushforward term over calls of k). A k = 1 model reads both keys as before.
  * ``unroll_grad`` (not in the paper; default off = the pushforward's detached chain): with U > 1 calls,
    backpropagate through the whole chain, so the loss of call c reaches the parameters through calls
    1..c-1 too (backpropagation through time over U calls; memory and backward cost ~U calls). Why: the
    final depth error of a k = 10 rollout (4.8 nm over the 500 design cases, most of them its training
    cases) is eight times that of one call from the simulator's own state (0.6 nm): each call is a little
    off in the same direction, which a one-call loss hardly sees under the Monte Carlo noise of one call's
    targets, while over U chained calls the error grows as U and the noise as sqrt(U)
    (benchmarks/small/physics/levers.md).
  * ``profile_loss_weight`` (not in the paper; 0 = the paper's loss) adds lambda times the mean squared error,
    in voxels^2, of the differentiable profile metrics (``nemsim.geometry.soft_profile``: etch depth, top
    and bottom width, mask loss) of every predicted state against its target. Why: the field MSE weighs a
    width error of a voxel at the hole's bottom like noise in a few voxels, and a model trained on it alone
    missed the neutral-Cl responses of the bottom width even on its training cases
    (benchmarks/small/physics/levers.md).
    A one-voxel metric error costs lambda; the field MSE of a trained model is ~2e-5.
  * ``pair_loss_weight`` (not in the paper; needs ``nemsim train --pair-data``): every optimizer step adds
    ``pairs_per_step`` sweep pairs (``nemsim.data.dataset.PairDataset``: two recipes that differ in one
    control group, simulated with one seed) to the batch, at the same time step for both members, and adds
    lambda times the MSE of the predicted difference of each pair (x_b - x_a, every predicted state)
    against the simulated one. Why: a Latin hypercube moves every control at once, and the field MSE of
    single cases weighs a control's response no more than the Monte Carlo noise around it; every model
    trained so far missed the responses to the angular exponents and the neutral flux
    (benchmarks/small/physics/levers.md). Simulated with common random numbers, a pair's difference holds
    the response with less of the noise, and the loss asks for it directly. lambda 0 with pair data: the
    members only join the batch. The pairs are drawn at random (a function of seed and step, so a resumed
    run draws the same pairs) and count toward the step's cost but not toward the epoch.
  * ``ema_decay`` (not in the paper; 0 = off) keeps an exponential moving average of the weights, and
    validation, ``best.pt`` and the final test use the average (``nemsim.training.average``: why, and the
    warm-up of its decay). 0.999 averages over about the last 1,000 steps.
  * ``max_train_minutes`` is a budget in wall-clock minutes (the equal-wall-time comparison of models that
    run at different speeds, e.g. NEMSim against its baselines or multi-step models of different k).
    It counts everything the training loop spends: optimizer steps, validation rollouts and checkpoint
    writes (metrics.csv and the summary record the validation share separately), summed over every
    ``--resume`` (``last.pt`` stores it; a killed run loses only the time since its last checkpoint).
    Not counted: loading data and building the model before the loop, and the final test. The run stops
    after the first optimizer step (or validation) at which the budget is reached, then validates once and
    writes best.pt / last.pt as at any other end (a budget raised on ``--resume`` goes on from the next
    epoch, as after ``max_steps``). With a wall budget the cosine's horizon is the budget
    itself: its progress is the fraction of the budget spent, so every model ends its decay at min_lr when
    its time runs out whatever its speed (a horizon in steps would leave a slow model at a high learning
    rate and hold a fast one at min_lr). The warm-up stays in steps (set ``warmup_steps``: the default of
    10 epochs can outlast a budget) and scales the cosine's value. The run then depends on the machine's
    speed, so a resumed budget run is not bit-identical to an uninterrupted one.
  * ``rollout_steps=None`` means the scene horizon (100); tests set a few steps to run in seconds.
  * ``channels_last`` / ``bf16`` are the CPU speed flags measured on the ``small`` scene; the defaults
    are the measured winners (DEFAULT_* below): bf16 autocast on, channels_last_3d off. bf16 applies to
    the training forward only; validation and test rollouts run in fp32.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Literal

# The faster setting of one NEMSim training step on the small scene: bf16 autocast on, channels_last_3d off
# (benchmarks/small/README.md, "Training-step precision and memory format").
DEFAULT_CHANNELS_LAST = False
DEFAULT_BF16 = True


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
    pairs_per_step: int = 4  # sweep pairs added to every batch when training with --pair-data
    max_epochs: int = 350  # epoch budget; the cosine spans warm-up end .. max_epochs
    max_steps: int | None = None  # optimizer-step budget; if set, training ends there and the cosine spans it
    max_train_minutes: float | None = None  # wall-clock budget (training + validation, summed over resumes);
    # if set, training ends when it is spent and the cosine spans it (instead of max_steps / max_epochs)
    warmup_steps: int | None = None  # warm-up length in steps; overrides warmup_epochs when set
    checkpoint_every: int | None = None  # also write last.pt every N steps (mid-epoch resume); None: epochs
    batches_per_epoch: int | None = None  # end each epoch after N batches (a random sample of the shuffled
    # training set): a large data set still validates, and keeps best.pt, every N steps; None = all of it
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
    # --- precision and device ---
    channels_last: bool = DEFAULT_CHANNELS_LAST  # torch.channels_last_3d for model and inputs
    bf16: bool = DEFAULT_BF16  # bfloat16 autocast for the training forward pass (rollouts stay fp32)
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
        if self.pairs_per_step < 1:
            raise ValueError(f"pairs_per_step must be >= 1, got {self.pairs_per_step}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must be in [0, 1) (0 = off), got {self.ema_decay}")
        if self.select_metric not in ("avg_rmse", "mse"):
            raise ValueError(f"select_metric={self.select_metric!r}; expected one of ['avg_rmse', 'mse']")

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

    text = Path(path).read_text()
    raw = yaml.safe_load(text) or {}
    if not isinstance(raw, dict):
        raise ValueError(f"{path}: expected a mapping of config keys, got {type(raw).__name__}")
    model_overrides = raw.pop("model", None) or {}
    if not isinstance(model_overrides, dict):
        raise ValueError(f"{path}: 'model' must be a mapping of model config overrides")
    return from_dict(raw), model_overrides


def to_json(cfg: TrainConfig) -> str:
    return json.dumps(asdict(cfg), sort_keys=True)
