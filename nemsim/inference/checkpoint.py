"""Checkpoints that carry their provenance (DESIGN.md "Checkpoints"; STYLE rule 4), and their one loader.

A checkpoint is one ``torch.save`` dict:

    format_version   int (CHECKPOINT_FORMAT)
    model_name       registry name ("nemsim", "fno", ...)
    model_config     asdict of the model's config dataclass (rebuilt from this, never from defaults)
    model_state      state_dict (DDP "module." prefixes stripped)
    weights_sha256   ``weights_digest(model_state)``, checked at load (absent in older checkpoints)
    scene            Scene.to_json()
    rules_sha256     sha256 of the compiled rules library the model was built with
    rules_source     that library's source YAML text (the model is rebuilt from this text)
    rules_perturbation  {"kind", "seed"} when the library was perturbed at tensor level, else None
    control_ranges   {name: {"kind", "low", "high", "unit"}} of nemsim.controls at training time
    summary          training summary (epochs, best epoch, best validation metric, seconds, config)
    metrics          test metrics ({} until ``nemsim evaluate`` fills them)
    sim_config       the simulator configuration the training data was made with (the data file's
                     ``generator`` attribute, parsed JSON), or None (unknown; checkpoints written before
                     this field); read it with ``checkpoint_sim_config``
    geometry         (optional) the features the training data drew, per kind: {kind: {"cd_nm": [lo, hi],
                     "mask_nm": [lo, hi]}} (also read from ``summary["geometry"]``; a record may be a list of
                     {"kind", "cd_nm", "mask_nm"} and a number stands for a single value); without it the
                     model was trained on its scene's own feature alone; read it with ``checkpoint_geometry``
    train_state      (last.pt only) optimizer state, lr-schedule step, epoch, RNG states, history

``read_checkpoint`` unpickles weights-only (``torch.load(weights_only=True)``: tensors, plain containers and
the numpy types on ``SAFE_GLOBALS``; a class, a function or ``os.system`` in the pickle is refused before it
runs) and verifies the weights: all finite, and equal to their recorded digest. ``load_checkpoint`` rebuilds
the model from the stored config and rules text and refuses a checkpoint whose rules library or scene differs
from the caller's, naming which. Every failure is a ``CheckpointError`` whose message names the file by its
base name only (safe to show a client) and says what is wrong.
"""

from __future__ import annotations

import hashlib
import logging
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from nemsim.geometry.feature import Feature
from nemsim.scenes import KINDS, Scene

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = 1

# what a checkpoint may hold besides tensors and plain containers: numpy scalars (training summaries) and
# numpy arrays (the numpy RNG state in last.pt's train_state)
SAFE_GLOBALS: list[Any] = [
    np._core.multiarray.scalar,  # type: ignore[attr-defined]
    np._core.multiarray._reconstruct,  # type: ignore[attr-defined]
    np.ndarray,
    np.dtype,
    *(getattr(np.dtypes, f"{kind}DType") for kind in (
        "Bool", "Int8", "Int16", "Int32", "Int64", "UInt8", "UInt16", "UInt32", "UInt64",
        "Float16", "Float32", "Float64", "Str",
    )),
]  # fmt: skip


class CheckpointError(ValueError):
    """The file is not a usable NEMSim checkpoint; the message names it by its base name only."""


class CheckpointNotFound(CheckpointError, FileNotFoundError):
    """The checkpoint file does not exist."""


class CheckpointMismatch(CheckpointError):
    """The checkpoint's rules library or scene differs from the one the caller supplied."""


@dataclass
class LoadedModel:
    model: nn.Module  # in eval mode, on the requested device
    name: str
    config: dict[str, Any]
    scene: Scene
    rules: Any  # nemsim.rules.compile.RuleTensors
    summary: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None
    raw: dict[str, Any] = field(default_factory=dict, repr=False)  # the checkpoint dict minus weights


@dataclass(frozen=True)
class GeometryRange:
    """The features of one kind a model was trained on: opening ``cd_nm`` and mask ``mask_nm``, each a
    closed interval (low, high) in nm (a single value: low == high)."""

    kind: str
    cd_nm: tuple[float, float]
    mask_nm: tuple[float, float]

    def contains(self, feature: Feature, rel_tol: float = 1e-6) -> bool:
        """Is ``feature`` (its kind, cd and mask) inside these intervals (``rel_tol``: float round-off)?"""
        return feature.kind == self.kind and all(
            lo * (1 - rel_tol) <= value <= hi * (1 + rel_tol)
            for value, (lo, hi) in ((feature.cd_nm, self.cd_nm), (feature.mask_nm, self.mask_nm))
        )

    def describe(self) -> str:
        """'hole, cd 40 nm, mask 80 nm' or with ranges 'cd 30..50 nm'."""
        def span(lo: float, hi: float) -> str:
            return f"{lo:g} nm" if lo == hi else f"{lo:g}..{hi:g} nm"

        return f"{self.kind}, cd {span(*self.cd_nm)}, mask {span(*self.mask_nm)}"

    def as_dict(self) -> dict[str, list[float]]:
        return {"cd_nm": [float(v) for v in self.cd_nm], "mask_nm": [float(v) for v in self.mask_nm]}


@dataclass(frozen=True)
class TrainedGeometry:
    """The features a checkpoint was trained on, per kind (``checkpoint_geometry``), and where that comes
    from (``source``: the checkpoint's record, or its scene's own feature as a single point)."""

    ranges: tuple[GeometryRange, ...]
    source: str

    @property
    def kinds(self) -> tuple[str, ...]:
        return tuple(r.kind for r in self.ranges)

    def range_of(self, kind: str) -> GeometryRange | None:
        return next((r for r in self.ranges if r.kind == kind), None)

    def contains(self, feature: Feature) -> bool:
        found = self.range_of(feature.kind)
        return found is not None and found.contains(feature)

    def as_dict(self) -> dict[str, Any]:
        """{"kinds": {kind: {"cd_nm": [lo, hi], "mask_nm": [lo, hi]}}, "source": ...} (``GET /model``)."""
        return {"kinds": {r.kind: r.as_dict() for r in self.ranges}, "source": self.source}


def _interval(value: Any, what: str) -> tuple[float, float]:
    """(lo, hi) from a number or a [lo, hi] pair of finite numbers > 0; ValueError naming ``what``."""
    pair = [value, value] if isinstance(value, int | float) and not isinstance(value, bool) else value
    if not (isinstance(pair, list | tuple) and len(pair) == 2):
        raise ValueError(f"{what} is a number or [low, high], got {value!r}")
    lo, hi = (float(v) for v in pair)
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
        raise ValueError(f"{what} needs finite 0 < low <= high, got {value!r}")
    return lo, hi


def _geometry_ranges(record: Any) -> tuple[GeometryRange, ...]:
    """GeometryRanges from a checkpoint's geometry record (module docstring: three accepted shapes)."""
    if isinstance(record, dict) and "kind" in record:
        record = [record]
    if isinstance(record, dict):
        record = [{"kind": kind, **(value if isinstance(value, dict) else {})}
                  for kind, value in record.items()]
    if not isinstance(record, list) or not record:
        raise ValueError(f"a geometry record is a dict per kind or a list of ranges, got "
                         f"{type(record).__name__}")
    out: list[GeometryRange] = []
    for item in record:
        kind = item.get("kind") if isinstance(item, dict) else None
        if kind not in KINDS:
            raise ValueError(f"geometry record: unknown kind {kind!r}; expected one of {KINDS}")
        if any(r.kind == kind for r in out):
            raise ValueError(f"geometry record: kind {kind!r} given twice")
        out.append(GeometryRange(kind, _interval(item.get("cd_nm"), f"{kind} cd_nm"),
                                 _interval(item.get("mask_nm"), f"{kind} mask_nm")))
    return tuple(out)


def checkpoint_geometry(source: LoadedModel | dict[str, Any]) -> TrainedGeometry:
    """The features a checkpoint was trained on (module docstring, ``geometry``): its record, else the
    scene's own feature as a single point (an unreadable record is logged and read the same way: the
    narrowest claim, so nothing beyond the scene's feature is called trained).

    Args:
        source: a ``LoadedModel`` or a raw checkpoint dict (with ``scene``).
    """
    raw = source.raw if isinstance(source, LoadedModel) else source
    scene = source.scene if isinstance(source, LoadedModel) else Scene.from_json(raw["scene"])
    record = raw.get("geometry")
    where = "the checkpoint's geometry record"
    if record is None:
        record = (raw.get("summary") or {}).get("geometry")
        where = "the checkpoint's training summary (geometry)"
    if record is not None:
        try:
            return TrainedGeometry(_geometry_ranges(record), where)
        except (TypeError, ValueError) as exc:
            log.warning("checkpoint geometry record unreadable (%s): the scene's feature alone is trained",
                        exc)
    own = Feature.of(scene)
    point = GeometryRange(own.kind, (own.cd_nm, own.cd_nm), (own.mask_nm, own.mask_nm))
    return TrainedGeometry((point,), f"the scene's own feature ({scene.name!r}; the checkpoint records no "
                                     "geometry range)")


def control_ranges() -> dict[str, dict[str, Any]]:
    """The 14 controls' transform kind and normalization bounds, stored with every checkpoint."""
    from nemsim.controls import CONTROL_SPECS

    return {
        s.name: {"kind": s.kind, "low": float(s.low), "high": float(s.high), "unit": s.unit}
        for s in CONTROL_SPECS
    }


def unwrap(model: nn.Module) -> nn.Module:
    """The bare module under DDP / torch.compile wrappers."""
    while hasattr(model, "module") and isinstance(model.module, nn.Module):
        model = model.module
    return getattr(model, "_orig_mod", model)


def checkpoint_id(path: str | Path) -> str:
    """The checkpoint's id: the first 12 hex digits of the file's SHA-256 (``GET /model``, calibrations and
    benchmark results name a checkpoint by it)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()[:12]


def weights_digest(state: dict[str, Any]) -> str:
    """SHA-256 over a state_dict's names, dtypes, shapes and bytes (sorted by name): what the file's weights
    must still be at load."""
    h = hashlib.sha256()
    for name in sorted(state):
        t = state[name]
        if not isinstance(t, torch.Tensor):
            continue
        t = t.detach().to("cpu").contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def checkpoint_dict(
    model: nn.Module,
    *,
    model_name: str,
    model_config: dict[str, Any],
    scene: Scene,
    rules: Any,
    rules_perturbation: dict[str, Any] | None = None,
    summary: dict[str, Any] | None = None,
    metrics: dict[str, Any] | None = None,
    train_state: dict[str, Any] | None = None,
    sim_config: dict[str, Any] | None = None,
    geometry: dict[str, Any] | list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The checkpoint dict (module docstring); ``geometry``: the trained features per kind, written only
    when given (``checkpoint_geometry`` checks it)."""
    if geometry is not None:
        _geometry_ranges(geometry)  # refuse to write a record the loader could not read
    state = {k: v.detach().to("cpu", copy=True).contiguous() for k, v in unwrap(model).state_dict().items()}
    return {
        "format_version": CHECKPOINT_FORMAT,
        "model_name": model_name,
        "model_config": dict(model_config),
        "model_state": state,
        "weights_sha256": weights_digest(state),
        "scene": scene.to_json(),
        "rules_sha256": str(rules.sha256),
        "rules_source": str(rules.source_text),
        "rules_perturbation": rules_perturbation,
        "control_ranges": control_ranges(),
        "summary": dict(summary or {}),
        "metrics": dict(metrics or {}),
        "train_state": train_state,
        "sim_config": None if sim_config is None else dict(sim_config),
        **({} if geometry is None else {"geometry": geometry}),
    }


def save_checkpoint(path: str | Path, model: nn.Module, **kwargs: Any) -> Path:
    """Write ``checkpoint_dict(model, **kwargs)`` atomically (tmp file + rename: a kill never leaves a
    half-written checkpoint)."""
    return write_checkpoint_dict(path, checkpoint_dict(model, **kwargs))


def write_checkpoint_dict(path: str | Path, ckpt: dict[str, Any]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(ckpt, tmp)
    os.replace(tmp, path)
    return path


def _unpickle(path: Path, name: str) -> Any:
    """``torch.load`` weights-only; CheckpointError for refused, damaged or foreign files."""
    try:
        with torch.serialization.safe_globals(SAFE_GLOBALS):
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        log.debug("refused checkpoint %s: %s", path, exc)
        unsafe = "Unsupported global" in str(exc) or "Weights only load failed" in str(exc)
        raise CheckpointError(
            f"checkpoint {name!r} holds Python objects other than tensors and plain data; refused "
            "(only weights-only checkpoints are read)"
            if unsafe
            else f"checkpoint {name!r} is damaged or not a PyTorch checkpoint"
        ) from exc
    except Exception as exc:  # noqa: BLE001 -- random bytes raise anything (IndexError, EOFError, ...)
        log.debug("unreadable checkpoint %s: %s: %s", path, type(exc).__name__, exc)
        raise CheckpointError(f"checkpoint {name!r} is empty, truncated or not a PyTorch checkpoint") from exc


def verify_weights(ckpt: dict[str, Any], name: str = "checkpoint") -> None:
    """CheckpointError unless every weight of ``ckpt["model_state"]`` is a finite tensor and, where the
    checkpoint records ``weights_sha256``, the weights still have that digest (a damaged file)."""
    state = ckpt.get("model_state")
    if not isinstance(state, dict) or not all(isinstance(t, torch.Tensor) for t in state.values()):
        raise CheckpointError(f"checkpoint {name!r} has no readable model weights (model_state)")
    for key, t in state.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise CheckpointError(
                f"checkpoint {name!r} is damaged: weight {key!r} holds NaN or Inf values; refused"
            )
    recorded = ckpt.get("weights_sha256")
    if recorded is not None and recorded != weights_digest(state):
        raise CheckpointError(
            f"checkpoint {name!r} is damaged: its weights differ from the digest recorded when it was "
            "written (weights_sha256); refused"
        )


def _check_weight_names(model: nn.Module, state: dict[str, Any], name: str) -> None:
    """CheckpointError naming the first missing or unexpected weight (a damaged or edited file)."""
    expected, found = set(model.state_dict()), set(state)
    missing, unexpected = sorted(expected - found), sorted(found - expected)
    if missing or unexpected:
        what = (f"weight {missing[0]!r} is missing" if missing else f"weight {unexpected[0]!r} is unexpected")
        more = len(missing) + len(unexpected) - 1
        also = f" ({more} more differ)" if more else ""
        raise CheckpointError(f"checkpoint {name!r} is damaged: {what}{also}; refused")


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The checkpoint dict, read weights-only, its format checked and its weights verified (module docstring).

    Raises:
        CheckpointNotFound: no such file. CheckpointError: refused, damaged or not a NEMSim checkpoint.
    """
    path = Path(path)
    name = path.name or "(empty name)"
    if not path.is_file():
        raise CheckpointNotFound(f"checkpoint {name!r} not found")
    ckpt = _unpickle(path, name)
    if not isinstance(ckpt, dict) or "format_version" not in ckpt:
        raise CheckpointError(f"checkpoint {name!r} is not a NEMSim checkpoint (no format_version)")
    version = ckpt["format_version"]
    if not isinstance(version, int) or version > CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"checkpoint {name!r} has format {version!r}; this NEMSim reads <= {CHECKPOINT_FORMAT}"
        )
    verify_weights(ckpt, name)
    return ckpt


def rules_from_checkpoint(ckpt: dict[str, Any]) -> Any:
    """Recompile the stored rules source text (and re-apply a stored tensor-level perturbation)."""
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import parse_rules

    rules = compile_rules(parse_rules(ckpt["rules_source"]))
    pert = ckpt.get("rules_perturbation")
    if pert and rules.sha256 != ckpt["rules_sha256"]:
        from nemsim.rules.perturb import perturb

        rules = perturb(rules, pert["kind"], int(pert["seed"]))
    elif pert and rules.perturbation == "none":  # spec-level perturbation (rate noise): text already noisy
        rules = rules.replace(perturbation=f"{pert['kind']}(seed={pert['seed']})")
    if rules.sha256 != ckpt["rules_sha256"]:
        raise CheckpointMismatch(
            f"rules: the checkpoint's stored rules text compiles to sha256 {rules.sha256[:12]}..., "
            f"but the checkpoint records {ckpt['rules_sha256'][:12]}... (rules compiler changed?)"
        )
    return rules


def check_compatible(ckpt: dict[str, Any], *, rules: Any = None, scene: Scene | str | None = None) -> None:
    """Raise CheckpointMismatch naming "rules" or "scene" if the caller's differ from the checkpoint's
    (``scene``: a Scene, compared whole, or a scene name)."""
    if rules is not None and str(rules.sha256) != ckpt["rules_sha256"]:
        raise CheckpointMismatch(
            f"rules library mismatch: checkpoint was trained with rules sha256 "
            f"{ckpt['rules_sha256'][:12]}..., the supplied rules have sha256 {str(rules.sha256)[:12]}..."
        )
    if isinstance(scene, str):
        stored_name = Scene.from_json(ckpt["scene"]).name
        if stored_name != scene:
            raise CheckpointMismatch(
                f"scene mismatch: checkpoint was trained on scene {stored_name!r}, expected scene {scene!r}"
            )
    elif scene is not None:
        stored = Scene.from_json(ckpt["scene"])
        if stored != scene:
            raise CheckpointMismatch(
                f"scene mismatch: checkpoint was trained on scene {stored.name!r} "
                f"(state {stored.state_shape}), the supplied scene is {scene.name!r} "
                f"(state {scene.state_shape})"
            )


def load_checkpoint(
    path: str | Path,
    *,
    rules: Any = None,
    scene: Scene | str | None = None,
    device: str | torch.device = "cpu",
) -> LoadedModel:
    """Rebuild a model from a checkpoint: stored config + stored rules text, weights loaded, eval mode.

    Args:
        path: a ``.pt`` file written by ``save_checkpoint`` (read by ``read_checkpoint``).
        rules: optional RuleTensors the caller intends to use; refused (CheckpointMismatch naming
            "rules") unless its sha256 equals the checkpoint's.
        scene: optional Scene or scene name; refused (CheckpointMismatch naming "scene") unless equal to the
            stored one (a name: the stored scene's name).
        device: where to put the model.
    Raises:
        CheckpointError (CheckpointNotFound, CheckpointMismatch): the message names the file and the fault.
    """
    from nemsim.registry import build_model

    path = Path(path)
    ckpt = read_checkpoint(path)
    try:
        check_compatible(ckpt, rules=rules, scene=scene)
        stored_scene = Scene.from_json(ckpt["scene"])
        stored_rules = rules_from_checkpoint(ckpt)
        model = build_model(ckpt["model_name"], stored_scene, stored_rules, dict(ckpt["model_config"]))
        _check_weight_names(model, ckpt["model_state"], path.name)
        model.load_state_dict(ckpt["model_state"])
    except CheckpointError:
        raise
    except Exception as exc:  # noqa: BLE001 -- any inconsistency inside the file means the same thing
        log.debug("cannot rebuild the model of %s: %s: %s", path, type(exc).__name__, exc)
        raise CheckpointError(
            f"checkpoint {path.name!r} does not match this NEMSim version: its model, rules or scene could "
            "not be rebuilt"
        ) from exc
    model.to(device).eval()
    raw = {k: v for k, v in ckpt.items() if k not in ("model_state", "train_state")}
    return LoadedModel(
        model=model,
        name=ckpt["model_name"],
        config=dict(ckpt["model_config"]),
        scene=stored_scene,
        rules=stored_rules,
        summary=dict(ckpt.get("summary") or {}),
        metrics=dict(ckpt.get("metrics") or {}),
        path=path,
        raw=raw,
    )


def checkpoint_sim_config(source: LoadedModel | dict[str, Any] | str | Path) -> dict[str, Any] | None:
    """The simulator configuration the checkpoint's training data was made with (the data file's
    ``generator`` JSON: simulator version, constants, seeds), or None if the checkpoint does not record it.

    Args:
        source: a ``LoadedModel``, a raw checkpoint dict, or the path of a checkpoint file.
    """
    if isinstance(source, LoadedModel):
        raw = source.raw
    elif isinstance(source, dict):
        raw = source
    else:
        raw = read_checkpoint(source)
    value = raw.get("sim_config")
    return None if value is None else dict(value)


def update_metrics(path: str | Path, metrics: dict[str, Any]) -> None:
    """Store test metrics into an existing checkpoint (``nemsim evaluate`` does this)."""
    ckpt = read_checkpoint(path)
    ckpt["metrics"] = {**(ckpt.get("metrics") or {}), **metrics}
    write_checkpoint_dict(path, ckpt)
