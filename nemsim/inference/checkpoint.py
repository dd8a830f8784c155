"""Checkpoints that carry their provenance (DESIGN.md "Checkpoints"; STYLE rule 4).

A checkpoint is one ``torch.save`` dict:

    format_version   int (CHECKPOINT_FORMAT)
    model_name       registry name ("nemsim", "fno", ...)
    model_config     asdict of the model's config dataclass (rebuilt from this, never from defaults)
    model_state      state_dict (DDP "module." prefixes stripped)
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
    train_state      (last.pt only) optimizer state, lr-schedule step, epoch, RNG states, history

``load_checkpoint`` rebuilds the model from the stored config and rules text and refuses a checkpoint
whose rules library or scene differs from the caller's, naming which. The model config carries every model
option, e.g. NEMSim's ``steps_per_call`` (absent in older checkpoints: the default, 1).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from nemsim.scenes import Scene

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = 1


class CheckpointMismatch(ValueError):
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
) -> dict[str, Any]:
    state = {k: v.detach().to("cpu", copy=True).contiguous() for k, v in unwrap(model).state_dict().items()}
    return {
        "format_version": CHECKPOINT_FORMAT,
        "model_name": model_name,
        "model_config": dict(model_config),
        "model_state": state,
        "scene": scene.to_json(),
        "rules_sha256": str(rules.sha256),
        "rules_source": str(rules.source_text),
        "rules_perturbation": rules_perturbation,
        "control_ranges": control_ranges(),
        "summary": dict(summary or {}),
        "metrics": dict(metrics or {}),
        "train_state": train_state,
        "sim_config": None if sim_config is None else dict(sim_config),
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


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The raw checkpoint dict; raises ValueError for a file that is not a NEMSim checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    # weights_only=False: the dict holds plain Python containers and optimizer state written by us.
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(ckpt, dict) or "format_version" not in ckpt:
        raise ValueError(f"{path} is not a NEMSim checkpoint (no format_version)")
    if ckpt["format_version"] > CHECKPOINT_FORMAT:
        raise ValueError(
            f"{path} has checkpoint format {ckpt['format_version']}; this NEMSim reads <= {CHECKPOINT_FORMAT}"
        )
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


def check_compatible(ckpt: dict[str, Any], *, rules: Any = None, scene: Scene | None = None) -> None:
    """Raise CheckpointMismatch naming "rules" or "scene" if the caller's differ from the checkpoint's."""
    if rules is not None and str(rules.sha256) != ckpt["rules_sha256"]:
        raise CheckpointMismatch(
            f"rules library mismatch: checkpoint was trained with rules sha256 "
            f"{ckpt['rules_sha256'][:12]}..., the supplied rules have sha256 {str(rules.sha256)[:12]}..."
        )
    if scene is not None:
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
    scene: Scene | None = None,
    device: str | torch.device = "cpu",
) -> LoadedModel:
    """Rebuild a model from a checkpoint: stored config + stored rules text, weights loaded, eval mode.

    Args:
        path: a ``.pt`` file written by ``save_checkpoint``.
        rules: optional RuleTensors the caller intends to use; refused (CheckpointMismatch naming
            "rules") unless its sha256 equals the checkpoint's.
        scene: optional Scene; refused (CheckpointMismatch naming "scene") unless equal to the stored one.
        device: where to put the model.
    """
    from nemsim.registry import build_model

    ckpt = read_checkpoint(path)
    check_compatible(ckpt, rules=rules, scene=scene)
    stored_scene = Scene.from_json(ckpt["scene"])
    stored_rules = rules_from_checkpoint(ckpt)
    model = build_model(ckpt["model_name"], stored_scene, stored_rules, dict(ckpt["model_config"]))
    model.load_state_dict(ckpt["model_state"])
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
        path=Path(path),
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
