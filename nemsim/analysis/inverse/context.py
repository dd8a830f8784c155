"""The model side of inverse design: a loaded checkpoint with what the reports need, differentiable
rollouts to the target state, and the search's no-gradient rollouts.

The search's no-gradient rollouts (screening, CMA-ES generations: most of a design's model time) run through
the OpenVINO runtime in the CPU's own precision (``search_runtime``, the service's own rollout path and
precision rule: bf16 where the core computes in it, else f32), about 2x faster than PyTorch f32 at the
search's batch on one CPU core; the recipes the search reports are rolled out again in
PyTorch f32 (``surrogate_search._final_recipes``), so every reported prediction and interval is the f32
model's. Where OpenVINO is missing or cannot export the model, the no-gradient rollouts are ``rollout_to``'s.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from nemsim.analysis.intervals import Calibration, Support

if TYPE_CHECKING:
    from nemsim.sim import SimConfig

log = logging.getLogger(__name__)


@dataclass
class InverseContext:
    """A loaded surrogate with what the design reports need."""

    model: torch.nn.Module
    scene: Any
    x0: torch.Tensor  # (2, D, H, W) float32 initial state
    calibration: Calibration | None
    support: Support
    model_id: str
    loaded: Any = None  # LoadedModel (rules and simulator configuration for verification)
    # the search's no-gradient rollouts: "openvino" (in the CPU's own precision,
    # ``resolve_precision("auto")``: bf16 where the core computes in it, else f32) or "torch-f32"
    search_runtime: str = "openvino"
    _runtime: Any = field(default=None, init=False, repr=False, compare=False)  # compiled on first use
    _lock: Any = field(default_factory=threading.Lock, init=False, repr=False, compare=False)

    def final_states(self, u: torch.Tensor, step: int) -> torch.Tensor:
        """The states at ``step`` (B, 2, D, H, W) of constant-control rollouts of u (B, 14) normalized
        controls, without gradients, through ``search_runtime`` (module docstring)."""
        with self._lock:  # one OpenVINO request per context; a service runs designs in threads
            runtime = self._search_runtime()
            with torch.no_grad():
                if runtime is None:
                    return rollout_to(self.model, self.x0, u, step)
                from nemsim.evaluation.rollout import rollout

                x0 = self.x0[None].expand(len(u), *self.x0.shape).contiguous()
                return rollout(runtime, x0, u, step, keep=False)  # type: ignore[arg-type]

    def _search_runtime(self) -> Any:
        """The OpenVINO runtime of the search (compiled once), or None: PyTorch's ``rollout_to``."""
        if self.search_runtime not in ("openvino", "torch-f32"):
            raise ValueError(f"search_runtime must be 'openvino' or 'torch-f32', got {self.search_runtime!r}")
        if self._runtime is None:
            self._runtime = False
            if self.search_runtime == "openvino" and callable(getattr(self.model, "precompute", None)):
                from nemsim.inference.precision import resolve_precision
                from nemsim.inference.runtime import compile_model, openvino_available

                if openvino_available():
                    runtime = compile_model(self.model, "openvino", resolve_precision("auto"),
                                            threads=torch.get_num_threads())
                    if runtime.backend == "openvino":
                        self._runtime = runtime
                    else:
                        log.info("inverse design: the search rolls out in torch f32: %s",
                                 runtime.fallback_reason)
        return self._runtime or None


def simulator_config(loaded: Any) -> SimConfig | None:
    """The SimConfig of the checkpoint's training data (``checkpoint_sim_config``), None for the simulator
    defaults (a checkpoint that records none)."""
    from nemsim.inference.checkpoint import checkpoint_sim_config
    from nemsim.sim import SimConfig

    return SimConfig.from_record(checkpoint_sim_config(loaded))


def load_inverse_context(checkpoint: str | Path) -> InverseContext:
    """Load a checkpoint, its initial state (its simulator configuration; a cross-section model's trench) and
    its calibration file."""
    from nemsim.analysis.intervals import calibration_for
    from nemsim.inference.checkpoint import checkpoint_id, load_checkpoint
    from nemsim.inference.predictor import served_scene
    from nemsim.sim import initial_state

    path = Path(checkpoint)
    if not path.is_file():
        raise ValueError(f"checkpoint {path} does not exist")
    loaded = load_checkpoint(path)
    scene = served_scene(loaded)  # a trench model's trench
    x0 = torch.from_numpy(np.asarray(initial_state(scene, simulator_config(loaded)), dtype=np.float32))
    cal = calibration_for(path)
    return InverseContext(
        model=loaded.model,
        scene=scene,
        x0=x0,
        calibration=cal,
        support=Support.from_record(cal.support if cal else None),
        model_id=f"{path.stem}@{checkpoint_id(path)}",
        loaded=loaded,
    )


def rollout_to(model: torch.nn.Module, x0: torch.Tensor, u: torch.Tensor, step: int) -> torch.Tensor:
    """The state at ``step`` of constant-control rollouts, differentiable in u (and the weights).

    Same predictions as ``nemsim.evaluation.rollout.rollout`` (multi-step models: chunks of k states per
    call, the last chunk cut at ``step``); only the states the next call needs are kept.

    Args:
        x0: (2, D, H, W) initial state. u: (B, 14) normalized controls.
    Returns:
        (B, 2, D, H, W).
    """
    from nemsim.evaluation.rollout import steps_per_call
    from nemsim.model.monotone import axis_eps_of, eps_field, monotone_eps_of, project

    B = u.shape[0]
    x = x0[None].expand(B, *x0.shape).to(u.dtype)  # (B, 2, D, H, W)
    fast = callable(getattr(model, "precompute", None))
    k = steps_per_call(model)
    cache = model.precompute(u) if fast else None  # type: ignore[operator]
    eps_of = monotone_eps_of(model, None)  # the rollout's monotone projection, if the model has one
    eps = None if eps_of is None else eps_field(x.shape, eps_of, axis_eps_of(model), x.dtype, x.device)
    running_max = x
    t = 0
    while t < step:
        n = min(k, step - t)
        if k > 1:
            states = model.predict(x, cache)[:, :n]  # type: ignore[operator]  # (B, n, 2, D, H, W)
        elif fast:
            states = model.step(x, cache)[:, None]  # type: ignore[operator]
        else:
            states = model(x, u)[:, None]
        if eps is None:
            x = states[:, -1]
        else:  # every state of the chunk updates the running maximum, as in the rollout
            for j in range(n):
                x, running_max = project(states[:, j], running_max, eps)
        t += n
    return x
