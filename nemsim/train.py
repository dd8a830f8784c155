"""Training entry point: ``nemsim train ...`` or, for DDP, ``torchrun --nproc-per-node 2 -m nemsim.train``.

Reads the data file and split manifest, seeds, builds the model from the registry, calls
``nemsim.training.loop.train`` and finally evaluates ``best.pt`` on the test split (stored in best.pt as
``metrics[setting]`` and in ``DIR/test_metrics.json``). Under torchrun (WORLD_SIZE > 1) the process group
is initialized here: gloo on CPU, NCCL on CUDA. Only rank 0 writes the log file and checkpoints.

Choices where the paper is silent:
  * the split manifest is ``--splits DIR/<setting>.json`` if given, else ``<data dir>/splits/<setting>.json``
    if present, else computed from the data file's own design with ``nemsim.data.splits.make_manifests``
    (the same seeded function the ``nemsim splits`` command uses); a manifest from disk must fit the data
    file (``nemsim.data.splits.resolve_manifest``);
  * ``--fraction F`` (data efficiency, [supp_data_efficiency]) keeps the training subset of
    ``nemsim.data.splits.data_efficiency_subsets`` for F; validation and test are unchanged;
  * the model's scene is the data file's scene.

This module is the process entry point (the ``nemsim train`` command and ``python -m nemsim.train`` under
torchrun), a peer of ``nemsim.cli``; the loop, its config and checkpoints live in ``nemsim.training`` and
``nemsim.inference.checkpoint``. What the model trains on is decided in one function, ``_load_data``.
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import sys
from collections.abc import Sequence
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Any, cast

log = logging.getLogger("nemsim.train")

SETTINGS = ("control-id", "ood-ar", "ood-cl", "ood-joint", "vis-50", "vis-60")


class TrainInputError(ValueError):
    """Bad command-line input for training (the CLI turns it into exit code 2)."""


def add_train_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", required=True, help="registered model name (see `nemsim models`)")
    p.add_argument("--data", required=True, type=Path, help="HDF5 dataset file (from `nemsim generate`)")
    p.add_argument("--setting", required=True, choices=SETTINGS, help="split setting")
    p.add_argument("--out", required=True, type=Path,
                   help="output directory (best.pt, last.pt, metrics.csv, train.log, test_metrics.json)")
    p.add_argument("--config", type=Path,
                   help="YAML/JSON: TrainConfig fields (lr, batch_size, ...); model overrides under `model:` "
                        "(default: the paper's values)")
    p.add_argument("--epochs", type=int, help="epoch budget (overrides max_epochs; default 350)")
    p.add_argument("--max-steps", type=int,
                   help="optimizer-step budget (overrides max_steps; default none): ends training there, "
                        "validates, and the learning-rate cosine spans it")
    p.add_argument("--max-minutes", type=float, metavar="M",
                   help="wall-clock budget in minutes (overrides max_train_minutes; default none): training "
                        "stops at the first optimizer step at which the run's wall time (training steps, "
                        "validation and checkpoints, summed over --resume) reaches M, validates and tests as "
                        "usual; the learning-rate cosine spans the budget (set warmup_steps in --config). "
                        "Example: --max-minutes 45 --resume continues a killed 45-minute run")
    p.add_argument("--fraction", type=float,
                   help="train on this data-efficiency fraction of the train split: 0.1, 0.2, 0.5 or 1 "
                        "(default 1)")
    p.add_argument("--extra-data", type=Path, action="append", default=[], metavar="FILE.h5",
                   help="also train on every complete case of this trajectory file (repeatable): a larger "
                        "design of the same scene, simulator configuration and rules, e.g. `nemsim "
                        "design --n 1500 --seed 43` simulated with `nemsim generate --controls`; validation "
                        "and test stay those of --data's split, so the paper protocol's cases are unchanged")
    p.add_argument("--pair-data", type=Path, metavar="FILE.h5",
                   help="sweep pairs to add to every batch (`pairs_per_step`, default 4) with a loss on "
                        "their predicted difference (`pair_loss_weight` in --config): the cases of this "
                        "file that share a simulator seed, e.g. `nemsim design --kind pairs --n 600 --seed "
                        "45` simulated with `nemsim generate --controls`; same scene, simulator "
                        "configuration and rules as --data")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--init-from", type=Path,
                   help="start from this checkpoint's weights (same model and rules); parameters it "
                        "lacks keep their initialization, e.g. the extra-step head of a steps_per_call > 1 "
                        "model started from a one-step checkpoint. A checkpoint of another scene is a warm "
                        "start too, e.g. a `small` model onto `paper` data (NEMSim's weights fit any grid: "
                        "convolutions, pooling and per-channel maps); the log names both scenes. Ignored "
                        "when --resume finds OUT/last.pt")
    p.add_argument("--complete-only", action="store_true",
                   help="train, validate and test on the split's cases that the data file holds complete, "
                        "e.g. a prefix of a design still being generated (default: refuse unfinished "
                        "cases); the log counts the dropped cases of each split")
    p.add_argument("--splits", type=Path,
                   help="directory of split manifests <setting>.json (default: <data dir>/splits if present, "
                        "else computed from the data file)")
    p.add_argument("--seed", type=int, help="override the seed (default 0)")
    p.add_argument("--bf16", action=argparse.BooleanOptionalAction, default=None,
                   help="bfloat16 autocast for the training forward pass (default on; rollouts stay fp32)")
    p.add_argument("--channels-last", action=argparse.BooleanOptionalAction, default=None,
                   help="channels_last_3d memory format (default off)")
    p.add_argument("--device", help="auto (default: cuda if available, else cpu), cpu, cuda, cuda:N")
    p.add_argument("--rollout-steps", type=int,
                   help="validation rollout length in transitions (default: full horizon, 100)")
    p.add_argument("--perturb", default="none",
                   help="rule-library perturbation (ablation): none (default), structure-only, "
                        "mechanism-shuffle, event-drop, rate-noise")
    p.add_argument("--perturb-seed", type=int, default=0, help="seed of the rule perturbation (default 0)")
    p.add_argument("--no-test", action="store_true", help="skip the final test evaluation of best.pt")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _apply_fraction(manifest: dict, fraction: float, tf: Any) -> dict:
    import numpy as np

    from nemsim.data.splits import data_efficiency_subsets

    if not 0 < fraction <= 1:
        raise TrainInputError(f"--fraction must be in (0, 1], got {fraction}")
    if fraction == 1:
        return manifest
    if "data_efficiency" in manifest:
        subsets = data_efficiency_subsets(manifest)
    else:
        row_of = {int(c): r for r, c in enumerate(np.asarray(tf.case_ids))}
        raw = np.asarray(tf.controls_raw)[[row_of[int(c)] for c in manifest["train"]]]
        subsets = data_efficiency_subsets(manifest, raw)
    key = min(subsets, key=lambda k: abs(float(k) - fraction))
    if abs(float(key) - fraction) > 1e-9:
        raise TrainInputError(
            f"--fraction {fraction} is not a data-efficiency subset; choose from {sorted(subsets)}"
        )
    return {**manifest, "train": list(subsets[key])}


def _init_from(model: Any, path: Path, name: str, rules: Any, scene: Any) -> None:
    """Load a checkpoint's weights into the fresh ``model`` (warm start); parameters the checkpoint lacks keep
    their initialization. Refuses another model or rules library, and parameters the model lacks or whose
    shapes differ. Another scene is accepted (a warm start, not a trained model of this scene) and logged:
    the trained model records the data file's scene."""
    from nemsim.inference.checkpoint import CheckpointMismatch, check_compatible, read_checkpoint
    from nemsim.scenes import Scene

    try:
        ckpt = read_checkpoint(path)
        check_compatible(ckpt, rules=rules)
        stored = Scene.from_json(ckpt["scene"])
    except (OSError, ValueError, TypeError, KeyError) as exc:  # CheckpointMismatch is a ValueError
        kind = "mismatch" if isinstance(exc, CheckpointMismatch) else "unreadable"
        raise TrainInputError(f"--init-from {path}: {kind}: {exc}") from None
    if ckpt["model_name"] != name:
        raise TrainInputError(f"--init-from {path}: a {ckpt['model_name']!r} checkpoint, training {name!r}")
    if stored != scene:
        log.warning("--init-from %s: weights of scene %r (%g nm voxels, state %s) start a model of scene %r "
                    "(%g nm voxels, state %s)", path, stored.name, stored.voxel_nm, stored.state_shape,
                    scene.name, scene.voxel_nm, scene.state_shape)
    state = ckpt["model_state"]
    cfg = getattr(model, "config", None)
    if cfg is not None and getattr(cfg, "angle_features", False) \
            and not ckpt["model_config"].get("angle_features", False):
        from nemsim.model.angle_features import widen_control_inputs

        try:  # the angle columns start at zero: the warm-started model predicts what the stored one did
            state = widen_control_inputs(state, model.state_dict(), cfg.context_dim)
        except ValueError as exc:
            raise TrainInputError(f"--init-from {path}: weights do not fit the model: {exc}") from None
        log.info("--init-from %s: the angle-feature columns of the control inputs start at zero", path)
    try:
        missing, unexpected = model.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shape mismatches
        first = str(exc).splitlines()[0]
        raise TrainInputError(f"--init-from {path}: weights do not fit the model: {first}") from None
    if unexpected:
        raise TrainInputError(f"--init-from {path}: parameters the model lacks: {sorted(unexpected)[:5]}")
    log.info("initialized from %s; kept the initialization of %d tensors: %s", path, len(missing),
             sorted(missing))


def _complete_only(manifest: dict, tf: Any) -> dict:
    """``manifest`` restricted to the cases ``tf`` holds complete (--complete-only); the drops are logged."""
    from nemsim.data.splits import complete_cases

    kept, dropped = complete_cases(manifest, tf.case_ids, tf.complete)
    counts = [f"{split} {len(kept[split])} of {len(kept[split]) + len(dropped[split])}"
              for split in ("train", "val", "test")]
    log.info("--complete-only: %s", ", ".join(counts))
    if not kept["train"] or not kept["val"]:
        raise TrainInputError(f"--complete-only: {tf.path} holds no complete case of the "
                              f"{'train' if not kept['train'] else 'val'} split")
    return kept


def _steps_per_call(model_overrides: dict[str, Any]) -> int:
    """k of the model being trained: the ``steps_per_call`` model override (NEMSim), else 1."""
    k = model_overrides.get("steps_per_call", 1)
    if not isinstance(k, int) or isinstance(k, bool) or k < 1:
        raise TrainInputError(f"model steps_per_call must be an integer >= 1, got {k!r}")
    return k


def _config_dict(cfg: Any) -> dict:
    return asdict(cfg) if is_dataclass(cfg) and not isinstance(cfg, type) else dict(cfg)


def _init_process_group() -> int:
    """Under torchrun (WORLD_SIZE > 1) join the process group (gloo on CPU, NCCL on CUDA); the rank."""
    import torch
    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend=backend)
        if torch.cuda.is_available():
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", 0)))
    return dist.get_rank() if dist.is_initialized() else 0


def _train_config(args: argparse.Namespace, rank: int) -> tuple[Any, dict[str, Any]]:
    """(TrainConfig, model overrides) from --config and the flags that override its fields."""
    from nemsim.training.config import TrainConfig, read_config_file

    try:
        cfg, model_overrides = read_config_file(args.config) if args.config else (TrainConfig(), {})
    except (OSError, ValueError) as exc:
        raise TrainInputError(f"--config {args.config}: {exc}") from None
    changes: dict[str, Any] = {}
    for arg, key in (("epochs", "max_epochs"), ("max_steps", "max_steps"),
                     ("max_minutes", "max_train_minutes"), ("seed", "seed"), ("bf16", "bf16"),
                     ("channels_last", "channels_last"), ("device", "device"),
                     ("rollout_steps", "rollout_steps")):
        if getattr(args, arg, None) is not None:
            changes[key] = getattr(args, arg)
    if args.no_progress or rank != 0:
        changes["progress"] = False
    try:
        return (cfg.replace(**changes) if changes else cfg), model_overrides
    except ValueError as exc:
        raise TrainInputError(str(exc)) from None


def _log_to_file(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(out / "train.log")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    if logging.getLogger().level > logging.INFO or logging.getLogger().level == logging.NOTSET:
        logging.getLogger().setLevel(logging.INFO)


def _check_like_data(path: Path, tf: Any, flag: str) -> None:
    """Refuse a further trajectory file (``flag`` = --extra-data or --pair-data) that is missing, has no
    complete case, or was not made by the main data file's scene, simulator configuration and rules."""
    from nemsim.data.hdf5 import open_trajectories

    if not Path(path).is_file():
        raise TrainInputError(f"{flag} {path} does not exist")
    with open_trajectories(path) as other:
        checks = (("scene", other.scene, tf.scene), ("rules", other.rules_sha256, tf.rules_sha256),
                  ("simulator configuration", other.generator.get("config"), tf.generator.get("config")),
                  ("states per case", other.n_states, tf.n_states))
        for what, theirs, ours in checks:
            if theirs != ours:
                raise TrainInputError(f"{flag} {path}: its {what} differs from {tf.path}'s")
        if not other.complete.any():
            raise TrainInputError(f"{flag} {path} has no complete case")


def _extra_train_set(path: Path, tf: Any, visible: int | None, unroll: int) -> Any:
    """Every complete case of an extra trajectory file as training items (``--extra-data``)."""
    from nemsim.data.dataset import TransitionDataset

    _check_like_data(path, tf, "--extra-data")
    return TransitionDataset(path, None, "train", visible_transitions=visible, unroll=unroll)


def _pair_set(path: Path, tf: Any, visible: int | None, unroll: int) -> Any:
    """The sweep pairs of a pair file (``--pair-data``; ``TrainConfig.pair_loss_weight``)."""
    from nemsim.data.dataset import PairDataset

    _check_like_data(path, tf, "--pair-data")
    try:
        return PairDataset(path, unroll=unroll, visible_transitions=visible)
    except ValueError as exc:
        raise TrainInputError(str(exc)) from None


def _load_data(args: argparse.Namespace, cfg: Any, model_overrides: dict[str, Any]) -> tuple[Any, dict, Any]:
    """(trajectory file, split manifest, TrainData) of --data, --setting, --splits and --fraction.

    The one place that decides what the model trains and validates on: every training item spans
    unroll_steps network calls of steps_per_call states each.
    """
    from nemsim.data.dataset import TrajectoryDataset, TransitionDataset, TransitionSets
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest
    from nemsim.training.loop import TrainData

    tf = open_trajectories(args.data)
    try:
        manifest, source = resolve_manifest(args.setting, args.data, tf.case_ids, tf.controls_raw,
                                            tf.scene.n_transitions, args.splits)
    except ValueError as exc:
        raise TrainInputError(str(exc)) from None
    log.info("split manifest: %s", source)
    if args.fraction is not None:
        manifest = _apply_fraction(manifest, args.fraction, tf)
    if args.complete_only:
        manifest = _complete_only(manifest, tf)
    for split, limit in (("val", cfg.val_cases), ("test", cfg.test_cases)):
        if limit is not None and split in manifest:
            manifest = {**manifest, split: list(manifest[split])[:limit]}
    visible = manifest.get("visible_transitions")
    unroll = cfg.unroll_steps * _steps_per_call(model_overrides)
    train_set: Any = TransitionDataset(args.data, manifest, "train", visible_transitions=visible,
                                       unroll=unroll)
    extra_sets = [_extra_train_set(path, tf, visible, unroll) for path in args.extra_data]
    if extra_sets:
        log.info("extra training data: %s", ", ".join(f"{e.path} ({len(e.rows)} cases)" for e in extra_sets))
        train_set = TransitionSets([train_set, *extra_sets])
    pairs = None if args.pair_data is None else _pair_set(args.pair_data, tf, visible, unroll)
    if pairs is not None:
        log.info("sweep pairs: %s (%d pairs), %d per step, pair_loss_weight %g", args.pair_data,
                 len(pairs.pairs), cfg.pairs_per_step, cfg.pair_loss_weight)
    elif cfg.pair_loss_weight > 0:
        raise TrainInputError("pair_loss_weight > 0 needs --pair-data FILE.h5 (sweep pairs: `nemsim design "
                              "--kind pairs`, then `nemsim generate --controls`)")
    data = TrainData(train=train_set, val=TrajectoryDataset(args.data, manifest, "val"), pairs=pairs)
    log.info("setting %s: %d train / %d val / %d test cases, visible transitions %s", args.setting,
             len(manifest["train"]), len(manifest["val"]), len(manifest["test"]), visible)
    return tf, manifest, data


def _rules(args: argparse.Namespace, tf: Any) -> tuple[Any, dict[str, Any] | None]:
    """(compiled rules, perturbation record or None): the library, optionally perturbed (--perturb)."""
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    rules = compile_rules(load_rules())
    tf.warn_if_other_rules(rules.sha256)
    if args.perturb == "none":
        return rules, None
    from nemsim.rules.perturb import perturb

    return perturb(rules, args.perturb, args.perturb_seed), {"kind": args.perturb, "seed": args.perturb_seed}


def _test_best(args: argparse.Namespace, out: Path, manifest: dict, scene: Any, steps: int | None) -> None:
    """Evaluate best.pt on the test split: into best.pt's metrics and OUT/test_metrics.json."""
    from nemsim.inference.checkpoint import load_checkpoint, update_metrics
    from nemsim.data.dataset import TrajectoryDataset
    from nemsim.evaluation.evaluate import evaluate, write_json

    loaded = load_checkpoint(out / "best.pt")
    test_set = cast(Sequence[Any], TrajectoryDataset(args.data, manifest, "test"))  # (case_id, states, u)
    result = evaluate(loaded.model, test_set, scene, steps=steps)
    update_metrics(out / "best.pt", {args.setting: result.to_json_dict()})
    write_json(result, out / "test_metrics.json", {"setting": args.setting})
    log.info("test: Avg RMSE %.5f, Final RMSE %.5f, CD %s", result.avg_rmse, result.final_rmse,
             f"{result.cd:.4f}" if result.cd is not None else "n/a")


def run(args: argparse.Namespace) -> int:
    import torch.distributed as dist

    from nemsim.registry import available_models, build_model, model_config
    from nemsim.training.loop import ModelMeta, seed_everything, train

    rank = _init_process_group()
    try:
        if args.model not in available_models():
            raise TrainInputError(f"unknown model {args.model!r}; expected one of {available_models()}")
        if not Path(args.data).is_file():
            raise TrainInputError(f"data file {args.data} does not exist")
        cfg, model_overrides = _train_config(args, rank)
        out = Path(args.out)
        if rank == 0:
            _log_to_file(out)
        tf, manifest, data = _load_data(args, cfg, model_overrides)
        scene = tf.scene
        rules, perturbation = _rules(args, tf)
        seed_everything(cfg.seed)
        model = build_model(args.model, scene, rules, model_overrides or None)
        if args.init_from is not None and not (args.resume and (out / "last.pt").is_file()):
            _init_from(model, Path(args.init_from), args.model, rules, scene)
        mcfg = _config_dict(model_config(args.model, scene, model_overrides or None))
        meta = ModelMeta(name=args.model, config=mcfg, scene=scene, rules=rules,
                         rules_perturbation=perturbation, sim_config=tf.generator or None)
        summary = train(cfg, model, data, out, meta, resume=args.resume)
        log.info("training done: best %s %.5g at epoch %d", summary["select_metric"], summary["best_val"],
                 summary["best_epoch"])
        if dist.is_initialized():
            dist.barrier()
        if rank == 0 and not args.no_test and (out / "best.pt").is_file() and manifest.get("test"):
            _test_best(args, out, manifest, scene, cfg.rollout_steps)
    finally:
        if dist.is_initialized():
            # the DDP wrapper and its reducer can sit in reference cycles: free them while the group they
            # use still exists, not at interpreter exit after it is gone (without this a rank died with
            # SIGABRT, "terminate called without an active exception", in about 1 of 10-30 test runs)
            gc.collect()
            dist.destroy_process_group()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m nemsim.train", description=__doc__.splitlines()[0])
    add_train_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return run(args)
    except TrainInputError as exc:
        print(f"nemsim train: {exc}", file=sys.stderr)  # noqa: T201
        return 2


if __name__ == "__main__":
    sys.exit(main())
