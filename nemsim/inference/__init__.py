"""The inference facade: one weights-only checkpoint loader, the runtimes and a predictor taking physical
controls -- what the service, the CLI and the bench use to run a trained model.

  ``checkpoint``   save / read / load checkpoints (weights-only, weights verified; ``CheckpointError``);
  ``eager``        the runtime interface and its PyTorch reference (``TorchRuntime``);
  ``runtime``      ``compile_model``: PyTorch eager, OpenVINO, or CUDA graphs (``cuda_graph``);
  ``precision``    the precision per device ("auto": bf16 where the hardware computes in it, else f32);
  ``predictor``    ``Predictor``: physical controls -> normalized once -> rollout -> profile metrics;
  ``range_check``  controls outside the training box (how far; allow, clip or refuse).

The names below are imported on first use (PEP 562), so ``import nemsim.inference`` (and importing one of
its modules) does not import torch's graph exporters, OpenVINO or the geometry code it does not need.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from nemsim.geometry.mesh import MEDIA_TYPES
    from nemsim.inference.checkpoint import (
        CheckpointError,
        CheckpointMismatch,
        CheckpointNotFound,
        LoadedModel,
        checkpoint_sim_config,
        load_checkpoint,
        read_checkpoint,
        save_checkpoint,
    )
    from nemsim.inference.predictor import (
        ControlSchedule,
        Prediction,
        Predictor,
        control_schedule,
        stability_warnings,
    )
    from nemsim.inference.range_check import POLICIES, Excursion, Refused
    from nemsim.inference.runtime import compile_model, openvino_available

__all__ = [
    "CheckpointError",
    "CheckpointMismatch",
    "CheckpointNotFound",
    "ControlSchedule",
    "Excursion",
    "LoadedModel",
    "MEDIA_TYPES",
    "POLICIES",
    "Prediction",
    "Predictor",
    "Refused",
    "checkpoint_sim_config",
    "compile_model",
    "control_schedule",
    "load_checkpoint",
    "openvino_available",
    "read_checkpoint",
    "save_checkpoint",
    "stability_warnings",
]


_CHECKPOINT = {"CheckpointError", "CheckpointMismatch", "CheckpointNotFound", "LoadedModel",
               "checkpoint_sim_config", "load_checkpoint", "read_checkpoint", "save_checkpoint"}  # fmt: skip
_PREDICTOR = {"ControlSchedule", "Prediction", "Predictor", "control_schedule", "stability_warnings"}
_RANGE_CHECK = {"POLICIES", "Excursion", "Refused"}
_RUNTIME = {"compile_model", "openvino_available"}


def __getattr__(name: str) -> Any:
    if name in _CHECKPOINT:
        from nemsim.inference import checkpoint as module
    elif name in _PREDICTOR:
        from nemsim.inference import predictor as module  # type: ignore[no-redef]
    elif name in _RANGE_CHECK:
        from nemsim.inference import range_check as module  # type: ignore[no-redef]
    elif name in _RUNTIME:
        from nemsim.inference import runtime as module  # type: ignore[no-redef]
    elif name == "MEDIA_TYPES":
        from nemsim.geometry import mesh as module  # type: ignore[no-redef]
    else:
        raise AttributeError(f"module 'nemsim.inference' has no attribute {name!r}")
    value = getattr(module, name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
