"""One training run end to end: data and split, model, ``loop.train``, then the test of ``best.pt``.

``run_training(job)`` is what `nemsim train` calls (``nemsim.cli.train`` turns the command line into a
``TrainJob``). It reads the data file and split manifest, seeds, builds the model from the registry, trains,
and evaluates ``best.pt`` on the test split (stored in best.pt as ``metrics[setting]`` and in
``OUT/test_metrics.json``). Under torchrun (WORLD_SIZE > 1) it joins the process group: gloo on CPU, NCCL on
CUDA; only rank 0 writes the log file and checkpoints.

Choices where the paper is silent:
  * the split manifest is ``<splits>/<setting>.json`` if ``splits`` is given, else
    ``<data dir>/splits/<setting>.json`` if present, else computed from the data file's own design
    (``nemsim.data.splits.resolve_manifest``, the seeded function `nemsim splits` uses); a manifest from
    disk must fit the data file;
  * ``fraction`` (data efficiency, [supp_data_efficiency]) keeps the training subset of
    ``nemsim.data.splits.data_efficiency_subsets``; validation and test are unchanged;
  * the model's scene is the data file's scene.
What the model trains on is decided in one function, ``_load_data``.
"""

from __future__ import annotations

import gc
import json
import logging
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, cast

from nemsim.training.config import TrainConfig

log = logging.getLogger("nemsim.train")


class TrainInputError(ValueError):
    """Bad input for a training run (the CLI prints it as one line, exit code 2)."""


@dataclass(frozen=True)
class TrainJob:
    """What one `nemsim train` run trains, on what, and where it writes."""

    model: str  # registered model name
    data: Path  # trajectory file (its scene is the model's)
    setting: str  # split setting (nemsim.data.splits.SETTINGS)
    out: Path  # best.pt, last.pt, metrics.csv, summary.json, train.log, test_metrics.json
    config: TrainConfig = field(default_factory=TrainConfig)
    model_overrides: dict[str, Any] = field(default_factory=dict)  # the config file's `model:` mapping
    splits: Path | None = None  # directory of <setting>.json manifests (default: next to the data)
    fraction: float | None = None  # data-efficiency subset of the train split (None: all of it)
    extra_data: tuple[Path, ...] = ()  # further trajectory files whose complete cases all train
    pair_data: Path | None = None  # sweep pairs for ``TrainConfig.pair_loss_weight``
    complete_only: bool = False  # keep only the split's cases the data file holds complete
    resume: bool = False  # continue from out/last.pt if present
    init_from: Path | None = None  # warm start from these weights (ignored when resuming from last.pt)
    perturb: str = "none"  # rule-library perturbation (ablation), nemsim.rules.perturb
    perturb_seed: int = 0
    test: bool = True  # evaluate best.pt on the test split at the end
    recipe: str | None = None  # the recipe file this run is a stage of (recorded in the summary)


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


def init_from(model: Any, path: Path, name: str, rules: Any, scene: Any) -> None:
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
    k_old = int(ckpt["model_config"].get("steps_per_call", 1) or 1)
    if cfg is not None and int(getattr(cfg, "steps_per_call", 1)) > k_old:
        from nemsim.model.decoder import extend_steps

        try:  # the first k_old states as the stored model predicts them, the rest along their trend
            state = extend_steps(state, model.state_dict())
        except ValueError as exc:
            raise TrainInputError(f"--init-from {path}: weights do not fit the model: {exc}") from None
        log.info("--init-from %s: the extra-step head grown from %d to %d states per call", path, k_old,
                 cfg.steps_per_call)
    try:
        missing, unexpected = model.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shape mismatches
        first = str(exc).splitlines()[0]
        raise TrainInputError(f"--init-from {path}: weights do not fit the model: {first}") from None
    if unexpected:
        raise TrainInputError(f"--init-from {path}: parameters the model lacks: {sorted(unexpected)[:5]}")
    log.info("initialized from %s; kept the initialization of %d tensors: %s", path, len(missing),
             sorted(missing))


def _provenance(job: TrainJob, manifest: dict) -> dict[str, Any]:
    """``ModelMeta.provenance`` of a run: its warm start, its recipe and the data it trained on (each file,
    the cases read from it, and a digest of what it holds: case ids, controls, simulator configuration)."""
    import hashlib

    import numpy as np

    from nemsim.data.hdf5 import open_trajectories

    def record(path: Path, role: str, cases: int | None = None) -> dict[str, Any]:
        with open_trajectories(path) as tf:
            h = hashlib.sha256()
            for part in (np.asarray(tf.case_ids), np.asarray(tf.controls_raw), np.asarray(tf.complete)):
                h.update(np.ascontiguousarray(part).tobytes())
            h.update(json.dumps(tf.generator, sort_keys=True, default=str).encode())
            n = int(np.count_nonzero(tf.complete)) if cases is None else cases
        return {"file": str(path), "role": role, "cases": n, "digest": h.hexdigest()[:16]}

    data = [record(Path(job.data), "splits", len(manifest.get("train", [])))]
    data += [record(Path(p), "extra") for p in job.extra_data]
    train_ids = [int(c) for c in manifest.get("train", [])]
    files: list[tuple[Path, list[int] | None]] = [(Path(job.data), train_ids)]
    files += [(Path(p), None) for p in job.extra_data]
    return {"init_from": None if job.init_from is None else str(job.init_from), "recipe": job.recipe,
            "data": data, "geometry": trained_geometry(files)}


def trained_geometry(files: Sequence[tuple[Path, Sequence[int] | None]]) -> dict[str, dict[str, list[float]]]:
    """The features the training cases drew, per kind: ``{kind: {"cd_nm": [lo, hi], "mask_nm": [lo, hi]}}``
    (the summary's ``geometry``, read by ``nemsim.inference.checkpoint.checkpoint_geometry``).

    Args:
        files: (trajectory file, the case ids that train, or None for all its complete cases) pairs. A file
            without a per-case ``geometry`` dataset holds its scene's own feature (``case_feature``).
    """
    import numpy as np

    from nemsim.data.hdf5 import open_trajectories

    spans: dict[str, list[list[float]]] = {}  # kind -> [[cd lo, cd hi], [mask lo, mask hi]]
    for path, ids in files:
        with open_trajectories(path) as tf:
            rows = np.flatnonzero(tf.complete) if ids is None else [tf.row_of(c) for c in ids]
            for row in rows:
                feature = tf.case_feature(int(row))
                span = spans.setdefault(feature.kind, [[feature.cd_nm] * 2, [feature.mask_nm] * 2])
                for pair, value in zip(span, (feature.cd_nm, feature.mask_nm), strict=True):
                    pair[0], pair[1] = min(pair[0], value), max(pair[1], value)
    return {kind: {"cd_nm": [float(v) for v in cd], "mask_nm": [float(v) for v in mask]}
            for kind, (cd, mask) in spans.items()}


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


def _log_to_file(out: Path) -> logging.Handler:
    """Send the log to OUT/train.log too (INFO at least); the caller removes the returned handler."""
    out.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(out / "train.log")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    if logging.getLogger().level > logging.INFO or logging.getLogger().level == logging.NOTSET:
        logging.getLogger().setLevel(logging.INFO)
    return handler


def _check_like_data(path: Path, tf: Any, flag: str) -> None:
    """Refuse a further trajectory file (``flag`` = --extra-data or --pair-data) that is missing, has no
    complete case, or was not made by the main data file's scene, simulator configuration and rules. The
    simulated domain and the random numbers may differ: a quarter-domain run (``SimConfig.domain``)
    simulates the same mean evolution between mirror walls (benchmarks/small/sim_quarter.md), and
    counter-based streams (``SimConfig.rng_mode``, the sweep pairs' common random numbers) draw the same
    distributions."""
    from nemsim.data.hdf5 import open_trajectories

    def physics(generator: dict) -> Any:
        config = generator.get("config")
        free = ("domain", "rng_mode")
        return {k: v for k, v in config.items() if k not in free} if isinstance(config, dict) else config

    if not Path(path).is_file():
        raise TrainInputError(f"{flag} {path} does not exist")
    with open_trajectories(path) as other:
        checks = (("scene", other.scene, tf.scene), ("rules", other.rules_sha256, tf.rules_sha256),
                  ("simulator configuration", physics(other.generator), physics(tf.generator)),
                  ("states per case", other.n_states, tf.n_states))
        for what, theirs, ours in checks:
            if theirs != ours:
                raise TrainInputError(f"{flag} {path}: its {what} differs from {tf.path}'s")
        if not other.complete.any():
            raise TrainInputError(f"{flag} {path} has no complete case")


def _extra_train_set(path: Path, tf: Any, visible: int | None, unroll: int, shape: dict[str, bool]) -> Any:
    """Every complete case of an extra trajectory file as training items (``--extra-data``)."""
    from nemsim.data.dataset import TransitionDataset

    _check_like_data(path, tf, "--extra-data")
    return TransitionDataset(path, None, "train", visible_transitions=visible, unroll=unroll, **shape)


def _memory_sets(sets: list[Any], val: Any, cfg: Any) -> tuple[Any, Any]:
    """The training sets and the validation trajectories decoded once into memory (``in_memory``): on the
    training GPU when they take at most half of its free memory, else in host memory."""
    import torch

    from nemsim.data.dataset import MemoryTrajectories, MemoryTransitions
    from nemsim.training.loop import pick_device

    device = pick_device(cfg.device)
    probe = MemoryTransitions.nbytes_of(sets)
    val_bytes = MemoryTransitions.nbytes_of([val])
    if device.type == "cuda" and probe + val_bytes > 0.5 * torch.cuda.mem_get_info(device)[0]:
        device = torch.device("cpu")
    device = device if device.type == "cuda" else torch.device("cpu")
    log.info("training set in memory: %d cases, %.2f GB float16 on %s; validation set %d cases, %.2f GB",
             sum(len(s.rows) for s in sets), probe / 1e9, device, len(val.rows), val_bytes / 1e9)
    return (MemoryTransitions(sets, device=device, progress=cfg.progress),
            MemoryTrajectories(val, device=device, progress=cfg.progress))


def _pair_set(path: Path, tf: Any, visible: int | None, unroll: int, shape: dict[str, bool]) -> Any:
    """The sweep pairs of a pair file (``--pair-data``), shaped as the training items (``shape``)."""
    from nemsim.data.dataset import PairDataset

    _check_like_data(path, tf, "--pair-data")
    try:
        return PairDataset(path, unroll=unroll, visible_transitions=visible, **shape)
    except ValueError as exc:
        raise TrainInputError(str(exc)) from None


def _load_data(job: TrainJob, cfg: TrainConfig) -> tuple[Any, dict, Any]:
    """(trajectory file, split manifest, TrainData) of the job's data, setting, splits and fraction.

    The one place that decides what the model trains and validates on: every training item spans
    unroll_steps network calls of steps_per_call states each.
    """
    from nemsim.data.dataset import TrajectoryDataset, TransitionDataset, TransitionSets
    from nemsim.data.hdf5 import open_trajectories
    from nemsim.data.splits import resolve_manifest
    from nemsim.training.loop import TrainData

    tf = open_trajectories(job.data)
    try:
        manifest, source = resolve_manifest(job.setting, job.data, tf.case_ids, tf.controls_raw,
                                            tf.scene.n_transitions, job.splits)
    except ValueError as exc:
        raise TrainInputError(str(exc)) from None
    log.info("split manifest: %s", source)
    if job.fraction is not None:
        manifest = _apply_fraction(manifest, job.fraction, tf)
    if job.complete_only:
        manifest = _complete_only(manifest, tf)
    for split, limit in (("val", cfg.val_cases), ("test", cfg.test_cases)):
        if limit is not None and split in manifest:
            manifest = {**manifest, split: list(manifest[split])[:limit]}
    visible = manifest.get("visible_transitions")
    unroll = cfg.unroll_steps * _steps_per_call(job.model_overrides)
    shape = {"symmetrize": cfg.symmetrize_targets,  # what every training state becomes (nemsim.symmetry)
             "quarter": (job.model_overrides or {}).get("domain") == "quarter",
             "section": (job.model_overrides or {}).get("domain") == "section"}
    try:
        train_set: Any = TransitionDataset(job.data, manifest, "train", visible_transitions=visible,
                                           unroll=unroll, **shape)
        extra_sets = [_extra_train_set(path, tf, visible, unroll, shape) for path in job.extra_data]
    except ValueError as exc:
        raise TrainInputError(str(exc)) from None
    if extra_sets:
        log.info("extra training data: %s", ", ".join(f"{e.path} ({len(e.rows)} cases)" for e in extra_sets))
    val_set: Any = TrajectoryDataset(job.data, manifest, "val")
    if cfg.in_memory:
        train_set, val_set = _memory_sets([train_set, *extra_sets], val_set, cfg)
    elif extra_sets:
        train_set = TransitionSets([train_set, *extra_sets])
    pairs = None if job.pair_data is None else _pair_set(job.pair_data, tf, visible, unroll, shape)
    if pairs is not None:
        log.info("sweep pairs: %s (%d pairs), %d per step, pair_loss_weight %g, response_loss_weight %g",
                 job.pair_data, len(pairs.pairs), cfg.pairs_per_step, cfg.pair_loss_weight,
                 cfg.response_loss_weight)
    elif cfg.pair_loss_weight > 0 or cfg.response_loss_weight > 0:
        raise TrainInputError("pair_loss_weight and response_loss_weight need --pair-data FILE.h5 (sweep "
                              "pairs: `nemsim design --kind pairs`, then `nemsim generate --controls`)")
    data = TrainData(train=train_set, val=val_set, pairs=pairs)
    log.info("setting %s: %d train / %d val / %d test cases, visible transitions %s", job.setting,
             len(manifest["train"]), len(manifest["val"]), len(manifest["test"]), visible)
    return tf, manifest, data


def _rules(job: TrainJob, tf: Any) -> tuple[Any, dict[str, Any] | None]:
    """(compiled rules, perturbation record or None): the library, optionally perturbed."""
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    rules = compile_rules(load_rules())
    tf.warn_if_other_rules(rules.sha256)
    if job.perturb == "none":
        return rules, None
    from nemsim.rules.perturb import perturb

    return perturb(rules, job.perturb, job.perturb_seed), {"kind": job.perturb, "seed": job.perturb_seed}


def _test_best(job: TrainJob, manifest: dict, scene: Any, cfg: TrainConfig) -> None:
    """Evaluate best.pt on the test split: into best.pt's metrics and OUT/test_metrics.json. With
    ``in_memory`` the test trajectories are decoded at once into the training device's memory; on a GPU
    they are rolled out there, ``val_batch_size`` at a time (the device's batch), on the CPU one at a time
    (the paper's timing)."""
    from nemsim.data.dataset import MemoryTrajectories, TrajectoryDataset
    from nemsim.evaluation.evaluate import evaluate, write_json
    from nemsim.inference.checkpoint import load_checkpoint, update_metrics
    from nemsim.training.loop import pick_device

    best = job.out / "best.pt"
    loaded = load_checkpoint(best)
    device = pick_device(cfg.device)
    test_set: Any = TrajectoryDataset(job.data, manifest, "test")  # (case_id, states, u)
    batch = cfg.resolved("cuda").val_batch_size if device.type == "cuda" else 1
    if cfg.in_memory:
        test_set = MemoryTrajectories(test_set, device=device, progress=cfg.progress)
    result = evaluate(loaded.model, cast(Sequence[Any], test_set), scene, steps=cfg.rollout_steps,
                      batch_size=batch, device=device)
    update_metrics(best, {job.setting: result.to_json_dict()})
    write_json(result, job.out / "test_metrics.json", {"setting": job.setting})
    log.info("test: Avg RMSE %.5f, Final RMSE %.5f, CD %s", result.avg_rmse, result.final_rmse,
             f"{result.cd:.4f}" if result.cd is not None else "n/a")


def run_training(job: TrainJob) -> dict[str, Any]:
    """Train ``job`` (resuming or warm-starting as it says) and test its best.pt; the training summary."""
    import torch.distributed as dist

    from nemsim.registry import available_models, build_model, model_config
    from nemsim.training.loop import ModelMeta, seed_everything, train

    rank = _init_process_group()
    handler = None
    try:
        if job.model not in available_models():
            raise TrainInputError(f"unknown model {job.model!r}; expected one of {available_models()}")
        if not Path(job.data).is_file():
            raise TrainInputError(f"data file {job.data} does not exist")
        cfg = job.config if rank == 0 else job.config.replace(progress=False)
        out = Path(job.out)
        if rank == 0:
            handler = _log_to_file(out)
        tf, manifest, data = _load_data(job, cfg)
        scene = tf.scene
        rules, perturbation = _rules(job, tf)
        seed_everything(cfg.seed)
        overrides = job.model_overrides or None
        model = build_model(job.model, scene, rules, overrides)
        if job.init_from is not None and not (job.resume and (out / "last.pt").is_file()):
            init_from(model, Path(job.init_from), job.model, rules, scene)
        mcfg = _config_dict(model_config(job.model, scene, overrides))
        meta = ModelMeta(name=job.model, config=mcfg, scene=scene, rules=rules,
                         rules_perturbation=perturbation, sim_config=tf.generator or None,
                         provenance=_provenance(job, manifest))
        summary = train(cfg, model, data, out, meta, resume=job.resume)
        log.info("training done: best %s %.5g at epoch %d", summary["select_metric"], summary["best_val"],
                 summary["best_epoch"])
        if dist.is_initialized():
            dist.barrier()
        if rank == 0 and job.test and (out / "best.pt").is_file() and manifest.get("test"):
            _test_best(job, manifest, scene, cfg)
    finally:
        if handler is not None:
            logging.getLogger().removeHandler(handler)
            handler.close()
        if dist.is_initialized():
            # the DDP wrapper and its reducer can sit in reference cycles: free them while the group they
            # use still exists, not at interpreter exit after it is gone (without this a rank died with
            # SIGABRT, "terminate called without an active exception", in about 1 of 10-30 test runs)
            gc.collect()
            dist.destroy_process_group()
    return summary
