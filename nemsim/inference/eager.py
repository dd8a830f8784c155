"""The runtime interface and its eager PyTorch reference (``TorchRuntime``).

A runtime has the model's inference API (``precompute(u) -> cache``,
``predict(x, cache) -> (B, k, 2, D, H, W)``, ``predict_into``, ``step``, ``__call__(x, u)``) and is
accepted by ``nemsim.evaluation.rollout.rollout`` in place of the model. The accelerated runtimes
(``nemsim.inference.runtime``: OpenVINO; ``nemsim.inference.cuda_graph``: CUDA graphs) are checked against
``TorchRuntime``; ``compile_model`` in ``nemsim.inference.runtime`` picks one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import nn

from nemsim.evaluation.rollout import steps_per_call
from nemsim.inference.precision import PRECISIONS, Precision
from nemsim.model.unpack import NO_FINISH, Finish

Backend = Literal["torch", "openvino", "cuda"]
BACKENDS: tuple[str, ...] = ("torch", "openvino", "cuda")


@dataclass(frozen=True)
class RuntimeConfig:
    backend: Backend = "openvino"  # "openvino" falls back to "torch" when unavailable
    precision: Precision = "f32"  # "bf16": autocast (torch) / inference precision hint (openvino)
    threads: int = 1  # OpenVINO inference threads per request (torch: set by the caller)

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown backend {self.backend!r}; expected one of {BACKENDS}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"unknown precision {self.precision!r}; expected one of {PRECISIONS}")
        if int(self.threads) < 1:
            raise ValueError(f"threads must be >= 1, got {self.threads}")


def model_precompute(model: nn.Module, u: torch.Tensor) -> dict[str, Any]:
    """``model.precompute(u)``, or ``{"u": u}`` for a model without the fast path (u: (B, 14))."""
    if callable(getattr(model, "precompute", None)):
        return model.precompute(u)  # type: ignore[operator]
    return {"u": u}


def model_predict(model: nn.Module, x: torch.Tensor, cache: dict[str, Any]) -> torch.Tensor:
    """The next k states (B, k, 2, D, H, W) from x (B, 2, D, H, W): ``model.predict``, else the k = 1 shims
    ``step(x, cache)[:, None]`` / ``model(x, cache["u"])[:, None]``."""
    if callable(getattr(model, "predict", None)):
        return model.predict(x, cache)  # type: ignore[operator]
    if callable(getattr(model, "step", None)) and callable(getattr(model, "precompute", None)):
        return model.step(x, cache)[:, None]  # type: ignore[operator]
    return model(x, cache["u"])[:, None]


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else ""



class Runtime:
    """Shared surface of the runtimes; subclasses implement ``precompute`` and ``predict``."""

    backend: str
    precision: str
    threads: int
    fallback_reason: str | None = None

    def __init__(self, model: nn.Module) -> None:
        self.model = model
        self.config = getattr(model, "config", None)
        self.k = steps_per_call(model)

    def precompute(self, u: torch.Tensor) -> Any:
        raise NotImplementedError

    def predict(self, x: torch.Tensor, cache: Any) -> torch.Tensor:
        raise NotImplementedError

    def predict_into(self, x: torch.Tensor, cache: Any, out: torch.Tensor,
                     finish: Finish = NO_FINISH) -> torch.Tensor:
        """The first n = out.shape[1] <= k predicted states written into out (B, n, 2, D, H, W), then
        ``finish``ed (``nemsim.model.unpack.Finish``; fused with the writing where a runtime can); out is
        returned (``rollout`` passes a slice of its trajectory buffer)."""
        _check_out(out, x, self.k)
        out.copy_(self.predict(x, cache)[:, : out.shape[1]])
        return finish.apply_(out)

    def step(self, x: torch.Tensor, cache: Any) -> torch.Tensor:
        """One transition (B, 2, D, H, W); only for k = 1 (use ``predict`` for k states per call)."""
        if self.k != 1:
            raise ValueError(f"step() needs steps_per_call = 1, this model predicts {self.k}; use predict()")
        return self.predict(x, cache)[:, 0]

    def __call__(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return self.step(x, self.precompute(u))

    def describe(self) -> dict[str, Any]:
        return {"backend": self.backend, "precision": self.precision, "threads": self.threads,
                "steps_per_call": self.k, "fallback_reason": self.fallback_reason}  # fmt: skip

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.describe()})"


class TorchRuntime(Runtime):
    """PyTorch eager (the reference); bf16 through CPU autocast."""

    backend = "torch"

    def __init__(self, model: nn.Module, precision: str = "f32", threads: int = 1) -> None:
        super().__init__(model)
        self.precision = precision
        self.threads = int(threads)

    def _ctx(self):
        return torch.autocast("cpu", dtype=torch.bfloat16, enabled=self.precision == "bf16")

    @torch.no_grad()
    def precompute(self, u: torch.Tensor) -> Any:
        return model_precompute(self.model, u)

    @torch.no_grad()
    def predict(self, x: torch.Tensor, cache: Any) -> torch.Tensor:
        with self._ctx():
            return model_predict(self.model, x, cache).float()

    @torch.no_grad()
    def predict_into(self, x: torch.Tensor, cache: Any, out: torch.Tensor,
                     finish: Finish = NO_FINISH) -> torch.Tensor:
        """fp32: the model's own ``predict_into`` where it has one (NEMSim writes and finishes the states
        in one fused pass, ``nemsim.model.unpack``); otherwise the copy of ``predict``."""
        into = getattr(self.model, "predict_into", None)
        if self.precision != "f32" or into is None:
            return super().predict_into(x, cache, out, finish)
        _check_out(out, x, self.k)
        return into(x, cache, out, finish)


def _check_out(out: torch.Tensor, x: torch.Tensor, k: int) -> None:
    """ValueError unless out is a (B, n <= k, 2, D, H, W) destination for the states after x."""
    if (out.dim() != x.dim() + 1 or out.shape[0] != x.shape[0] or not 1 <= out.shape[1] <= k
            or out.shape[2:] != x.shape[1:]):
        raise ValueError(f"out must be (B, n <= {k}, *{tuple(x.shape[1:])}) for x {tuple(x.shape)}, "
                         f"got {tuple(out.shape)}")
