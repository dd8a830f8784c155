"""Safe checkpoint loading for the service: no code from the file runs, and no failure leaks a path.

`torch.load(weights_only=True)` unpickles only tensors, plain containers and the globals on
`ALLOWED_GLOBALS` (numpy scalars and their dtypes, which training summaries may carry); anything else
in the pickle (a class, a function, `os.system`) is refused before it runs. NEMSim checkpoints are
plain dicts of tensors, numbers, strings and lists (`nemsim.inference.checkpoint`), so every checkpoint
written by `save_checkpoint` loads, the shipped one included.

`load_checkpoint_safely` is `nemsim.inference.checkpoint.load_checkpoint` with the safe read: the model
is rebuilt with the same library functions (`check`, `rules_from_checkpoint`, `build_model`). Every
failure becomes `CheckpointError`, whose message names the file by its base name only and says what is
wrong in words a client may see; the full exception goes to the server log.
"""

from __future__ import annotations

import logging
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import torch

log = logging.getLogger(__name__)

ALLOWED_GLOBALS: list[Any] = [
    np._core.multiarray.scalar,  # type: ignore[attr-defined]  # numpy scalars, e.g. np.float64(0.03)
    np.dtype,
    np.dtypes.Float64DType,
    np.dtypes.Float32DType,
    np.dtypes.Int64DType,
    np.dtypes.Int32DType,
    np.dtypes.BoolDType,
]


class CheckpointError(RuntimeError):
    """The checkpoint cannot be served; the message is safe to show to clients (no paths)."""


def read_checkpoint_safely(path: str | Path) -> dict[str, Any]:
    """The checkpoint dict, unpickled with the weights-only loader; CheckpointError otherwise."""
    path = Path(path)
    name = path.name or "(empty name)"
    if not path.is_file():
        raise CheckpointError(f"checkpoint {name!r} not found")
    try:
        with torch.serialization.safe_globals(ALLOWED_GLOBALS):
            ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        log.error("refused checkpoint %s: %s", path, exc)
        unsafe = "Unsupported global" in str(exc) or "Weights only load failed" in str(exc)
        raise CheckpointError(
            f"checkpoint {name!r} holds Python objects other than tensors and plain data; refused "
            "(only weights-only checkpoints are served)"
            if unsafe
            else f"checkpoint {name!r} is damaged or not a PyTorch checkpoint"
        ) from None
    except Exception as exc:  # noqa: BLE001 -- random bytes raise anything (IndexError, EOFError, ...)
        log.error("unreadable checkpoint %s: %s: %s", path, type(exc).__name__, exc)
        raise CheckpointError(
            f"checkpoint {name!r} is empty, truncated or not a PyTorch checkpoint"
        ) from None
    if not isinstance(ckpt, dict) or "format_version" not in ckpt:
        raise CheckpointError(f"checkpoint {name!r} is not a NEMSim checkpoint (no format_version)")
    from nemsim.inference.checkpoint import CHECKPOINT_FORMAT

    if not isinstance(ckpt["format_version"], int) or ckpt["format_version"] > CHECKPOINT_FORMAT:
        raise CheckpointError(
            f"checkpoint {name!r} has format {ckpt['format_version']!r}; "
            f"this server reads <= {CHECKPOINT_FORMAT}"
        )
    return ckpt


def load_checkpoint_safely(path: str | Path) -> Any:
    """A `nemsim.inference.checkpoint.LoadedModel` from a safely read checkpoint (CheckpointError)."""
    from nemsim.inference.checkpoint import LoadedModel, rules_from_checkpoint
    from nemsim.registry import build_model
    from nemsim.scenes import Scene

    path = Path(path)
    ckpt = read_checkpoint_safely(path)
    try:
        scene = Scene.from_json(ckpt["scene"])
        rules = rules_from_checkpoint(ckpt)
        model = build_model(ckpt["model_name"], scene, rules, dict(ckpt["model_config"]))
        model.load_state_dict(ckpt["model_state"])
    except Exception as exc:  # noqa: BLE001 -- any inconsistency inside the file means the same thing
        log.error("cannot rebuild the model of %s: %s: %s", path, type(exc).__name__, exc)
        raise CheckpointError(
            f"checkpoint {path.name!r} does not match this NEMSim version (model, rules or scene could not "
            "be rebuilt; the server log has details)"
        ) from None
    model.eval()
    raw = {k: v for k, v in ckpt.items() if k not in ("model_state", "train_state")}
    return LoadedModel(
        model=model,
        name=str(ckpt["model_name"]),
        config=dict(ckpt["model_config"]),
        scene=scene,
        rules=rules,
        summary=dict(ckpt.get("summary") or {}),
        metrics=dict(ckpt.get("metrics") or {}),
        path=path,
        raw=raw,
    )
