"""Low-overhead CPU inference runtime for a surrogate's step network (``compile_model``).

``compile_model(model, backend, precision, threads)`` returns a **predictor**: an object with the model's
inference API (``precompute(u) -> cache``, ``predict(x, cache) -> (B, k, 2, D, H, W)``, ``step(x, cache)``,
``__call__(x, u)``, ``config``) that ``nemsim.evaluation.rollout.rollout`` accepts in place of the model.

Backends:
  * ``"torch"``: PyTorch eager, the **reference**. ``bf16`` runs under ``torch.autocast("cpu", bfloat16)``
    (the model keeps its rule side in fp32 itself).
  * ``"openvino"``: the per-step part exported to OpenVINO (``openvino`` is the optional extra
    ``nemsim[fast]``) and run by its CPU plugin; ``bf16`` is its ``INFERENCE_PRECISION_HINT``. Falls back
    to ``"torch"`` with a logged reason when openvino is not installed or the export fails; the predictor's
    ``backend`` attribute says what actually runs, ``fallback_reason`` why.

What is exported (choice): ``step(x, cache)`` with the control-derived tensors of ``cache`` as graph inputs,
not ``forward(x, u)``. ``precompute(u)`` stays in PyTorch fp32 (it runs once per distinct control vector; the
rule kinetics are not bf16-friendly) and feeds the graph. Which cache entries are inputs is found by
evaluating ``precompute`` at two random control vectors: entries that differ are inputs, the others (rule
buffers, weight products) are folded into the graph as constants. Models without ``precompute``
(baselines) are exported as ``forward(x, u)`` with ``u`` the input.
Shapes are static: one OpenVINO model is converted, reshaped to the call's input shapes (the trace alone
leaves them dynamic, and the plugin then redoes shape arithmetic and memory planning on every call) and
compiled per (state shape incl. batch, input shapes) on first use and kept, so a scene at batch 1 and 16
compiles twice. Infer requests (not thread-safe; the
compiled model is shared) come from a pool: a call takes an idle one or makes one, and gives it back, so
there are as many as calls ever ran at once, not one per thread that ever called (a server's thread pool).
Outputs are copied out of the request's buffers, so a kept trajectory is never overwritten by the next step.

Threads (choice): ``threads`` is OpenVINO's ``INFERENCE_NUM_THREADS`` with one stream and CPU pinning off
(pinned single-thread streams of concurrent requests can land on the same core; unpinned, the OS spreads
them). The default is 1: two concurrent 1-thread rollouts fill a 2-core machine without oversubscribing it,
and 2 threads were slower per rollout on the shared machine measured (below). For ``"torch"`` the thread
count is process-global (``torch.set_num_threads``) and left to the caller; ``threads`` is only recorded.

Measured (``small``, shipped checkpoint, batch 1, 100-step rollout, CPU seconds, medians of 5 and 7
interleaved repeats in two runs; AMD EPYC with AVX-512 BF16, no AMX, 2 cores shared with other jobs at load
4-8): torch f32 1.085 / 1.127 s (the reference), torch bf16 0.98x / 0.97x, openvino f32 1.04x / 1.05x (max |Δ|
1.6e-6 over the trajectory), openvino bf16 1.16x / 1.06x (max |Δ| 0.020, RMS Δ 1.1e-3; Avg RMSE against the
simulator +0.8 % on 2 control-id test cases). With 2 threads under that load: torch f32 0.09x
(spin-waiting), openvino f32 0.59x / 0.66x, bf16 0.69x / 0.64x. At batch 16 (per trajectory) openvino f32
was 0.78x of torch, bf16 1.04x. That is less than an earlier measurement (1.35x / 1.63x): the eager path
is already fast here (prepacked oneDNN convolutions, fused MRC increment), and this CPU has no AMX for bf16.
Export + compile: a few CPU seconds per (shape, precision).

Multi-step models: ``predict`` returns the next k = ``model.config.steps_per_call`` states; a model that only
has ``step`` is shimmed as ``step(x, cache)[:, None]`` (k = 1).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils import _pytree as pytree

from nemsim.controls import N_CONTROLS

log = logging.getLogger(__name__)

Backend = Literal["torch", "openvino"]
Precision = Literal["f32", "bf16"]
BACKENDS: tuple[str, ...] = ("torch", "openvino")
PRECISIONS: tuple[str, ...] = ("f32", "bf16")


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


def openvino_available() -> bool:
    try:
        import openvino  # noqa: F401
    except ImportError:
        return False
    return True


def steps_per_call(model: nn.Module) -> int:
    """k: states one network call predicts (``model.config.steps_per_call``, 1 when absent)."""
    return int(getattr(getattr(model, "config", None), "steps_per_call", 1) or 1)


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


@contextlib.contextmanager
def _export_kernels() -> Iterator[None]:
    """Swap eager-tuned kernels for standard ops with the same values while tracing for export: the layers'
    direct oneDNN calls (``aten.mkldnn_convolution``, prepacked weights: not convertible) become
    ``F.conv3d``, the decoder's broadcast-copy 2x up-sampling becomes ``F.interpolate(nearest)``
    (OpenVINO ran the 8-D broadcast as a slow element-wise multiply), and GroupNorm runs on a 4-D view
    (``_group_norm_4d``). Module globals are swapped for the
    duration of the trace (under the predictor's lock); an eager rollout running meanwhile in another
    thread takes the standard path too: same values, only slower for that moment."""
    from nemsim.model import decoder, layers

    swaps = [(mod, name, new) for mod, name, new in
             ((decoder, "upsample2", _upsample_nearest), (layers, "_onednn_ok", _never),
              (layers, "apply_group_norm", _group_norm_4d))
             if hasattr(mod, name)]  # fmt: skip
    originals = [getattr(mod, name) for mod, name, _ in swaps]
    for mod, name, new in swaps:
        setattr(mod, name, new)
    try:
        yield
    finally:
        for (mod, name, _), old in zip(swaps, originals, strict=True):
            setattr(mod, name, old)


def _never(x: torch.Tensor) -> bool:
    return False


def _group_norm_4d(gn: nn.GroupNorm, x: torch.Tensor) -> torch.Tensor:
    """GroupNorm of a 5-D x (B, C, D, H, W) computed on its (B, C, D, H·W) view: the same statistics and
    values. OpenVINO's CPU plugin fuses the per-channel affine with the SiLU that follows into one
    element-wise kernel, which it ran several times slower on 5-D tensors than on 4-D ones (measured on
    GroupNorm + SiLU of a (1, 12, 34, 14, 14) tensor; most of the step graph's normalization time)."""
    if x.dim() != 5:
        return F.group_norm(x, gn.num_groups, gn.weight, gn.bias, gn.eps)
    return F.group_norm(x.flatten(3), gn.num_groups, gn.weight, gn.bias, gn.eps).view(x.shape)


def _upsample_nearest(h: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    return F.interpolate(h, size=size, mode="nearest")  # (B, C, *size)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0][:200] if text else ""


class _Predictor:
    """Shared surface of the predictors; subclasses implement ``precompute`` and ``predict``."""

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


class TorchPredictor(_Predictor):
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


class _StepGraph(nn.Module):
    """predict(x, cache) with the cache's variable leaves as inputs and its constant leaves as buffers."""

    def __init__(self, model: nn.Module, spec: Any, leaves: list[Any], variable: list[int]) -> None:
        super().__init__()
        self.model = model
        self.spec = spec
        self.variable = variable
        self.leaves = list(leaves)  # constants in place; the variable slots are replaced per call

    def forward(self, x: torch.Tensor, *inputs: torch.Tensor) -> torch.Tensor:
        leaves = list(self.leaves)
        for i, t in zip(self.variable, inputs, strict=True):
            leaves[i] = t
        return model_predict(self.model, x, pytree.tree_unflatten(leaves, self.spec))  # (B, k, 2, D, H, W)


@dataclass
class _OVCache:
    """What ``OpenVINOPredictor.precompute`` returns: the control-derived graph inputs as numpy arrays."""

    inputs: list[Any]  # numpy arrays, order of the graph's inputs after x
    batch: int
    torch_cache: Any  # the model's own cache (used if the export fails and the predictor falls back)


class OpenVINOPredictor(_Predictor):
    """The step graph compiled by OpenVINO's CPU plugin (module docstring)."""

    backend = "openvino"
    # OpenVINO 2026.4's CPU plugin crashed (SIGSEGV in compile_model) on the f32 NEMSim step graph at batch
    # > 1 with its subgraph "snippets" on; disabling them fixed it (speed: module docstring).
    extra_properties: dict[str, Any] = {"SNIPPETS_MODE": "DISABLE"}

    def __init__(self, model: nn.Module, precision: str = "f32", threads: int = 1) -> None:
        import openvino as ov

        super().__init__(model)
        self.precision = precision
        self.threads = int(threads)
        self._ov = ov
        self._core = ov.Core()
        self._compiled: dict[tuple, Any] = {}
        self._lock = threading.Lock()
        self._idle: dict[tuple, list[Any]] = {}  # shape key -> infer requests not in use
        self._fallback: TorchPredictor | None = None
        self._spec, self._variable = self._cache_layout()

    def _cache_layout(self) -> tuple[Any, list[int]]:
        """(pytree spec of precompute's output, indices of the leaves that depend on u)."""
        g = torch.Generator().manual_seed(0)
        u1, u2 = (torch.rand(1, N_CONTROLS, generator=g) * 2 - 1 for _ in range(2))
        with torch.no_grad():
            l1, spec = pytree.tree_flatten(model_precompute(self.model, u1))
            l2, _ = pytree.tree_flatten(model_precompute(self.model, u2))
        variable = [
            i for i, (a, b) in enumerate(zip(l1, l2, strict=True))
            if isinstance(a, torch.Tensor) and (a.shape != b.shape or not torch.equal(a, b))
        ]  # fmt: skip
        return spec, variable

    @torch.no_grad()
    def precompute(self, u: torch.Tensor) -> _OVCache:
        leaves, spec = pytree.tree_flatten(model_precompute(self.model, u))
        if spec != self._spec:
            raise ValueError("precompute(u) changed structure since compile; recompile the model")
        cache = pytree.tree_unflatten(leaves, spec)
        return _OVCache([leaves[i].detach().float().contiguous().numpy() for i in self._variable],
                        int(u.shape[0]), cache)  # fmt: skip

    def _compile(self, x: torch.Tensor, cache: _OVCache, key: tuple) -> Any:
        ov = self._ov
        # the tracer cannot record inference tensors (a caller under torch.inference_mode): plain copies
        with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the tracer's notes on shape checks are not the user's concern
            leaves, _ = pytree.tree_flatten(cache.torch_cache)
            leaves = [t.detach().clone() if isinstance(t, torch.Tensor) else t for t in leaves]
            graph = _StepGraph(self.model, self._spec, leaves, self._variable).eval()
            example = (x.detach().float().clone(), *(torch.from_numpy(a.copy()) for a in cache.inputs))
            with _export_kernels():
                ov_model = ov.convert_model(graph, example_input=example)  # TorchScript trace
            # the trace leaves every input dimension dynamic: fixing them lets the plugin fold the shape
            # arithmetic and plan memory and kernels once instead of on every call
            ov_model.reshape({i: ov.PartialShape([int(n) for n in t.shape]) for i, t in enumerate(example)})
        props = {
            "INFERENCE_NUM_THREADS": self.threads,
            "NUM_STREAMS": 1,
            "PERFORMANCE_HINT": "LATENCY",
            "ENABLE_CPU_PINNING": False,
            # explicit: the CPU plugin's default is bf16 on CPUs with bf16 instructions
            "INFERENCE_PRECISION_HINT": "bf16" if self.precision == "bf16" else "f32",
            **self.extra_properties,
        }
        compiled = self._core.compile_model(ov_model, "CPU", props)
        log.info("openvino: compiled the step graph for x %s (%s, %d thread(s))", tuple(x.shape),
                 self.precision, self.threads)  # fmt: skip
        return compiled

    def _acquire(self, x: torch.Tensor, cache: _OVCache) -> tuple[tuple, Any]:
        """(key, an idle infer request for this shape): from the pool, else a new one (compiling first)."""
        key = (tuple(x.shape), tuple(a.shape for a in cache.inputs))
        with self._lock:
            idle = self._idle.setdefault(key, [])
            if idle:
                return key, idle.pop()
            compiled = self._compiled.get(key)
            if compiled is None:
                compiled = self._compiled[key] = self._compile(x, cache, key)
            return key, compiled.create_infer_request()

    def _release(self, key: tuple, req: Any) -> None:
        with self._lock:
            self._idle[key].append(req)

    def predict(self, x: torch.Tensor, cache: Any) -> torch.Tensor:
        if not isinstance(cache, _OVCache):
            raise TypeError(f"cache must come from this predictor's precompute(), got {type(cache).__name__}")
        if x.shape[0] != cache.batch:
            raise ValueError(f"the cache holds controls for batch {cache.batch}, x has batch {x.shape[0]}")
        if self._fallback is not None:
            return self._fallback.predict(x, cache.torch_cache)
        try:
            key, req = self._acquire(x, cache)
        except Exception as exc:  # noqa: BLE001 -- an export failure falls back to the reference path
            self.fallback_reason = f"openvino export failed: {type(exc).__name__}: {_first_line(exc)}"
            log.warning("runtime: using torch instead of openvino: %s", self.fallback_reason)
            self._fallback = TorchPredictor(self.model, self.precision, self.threads)
            self.backend = "torch"
            return self._fallback.predict(x, cache.torch_cache)
        try:
            xin = x.detach().float().contiguous().numpy()
            out = req.infer([xin, *cache.inputs], share_inputs=True, share_outputs=True)[0]
            # copied out of the request's buffer into memory from torch's allocator, which reuses freed
            # blocks: numpy's ``out.copy()`` maps fresh pages for every multi-MB result (page faults cost
            # several times the copy itself)
            res = torch.empty(out.shape, dtype=torch.float32)  # (B, k, 2, D, H, W)
            res.numpy()[...] = out
            return res
        finally:
            self._release(key, req)


def compile_model(
    model: nn.Module,
    backend: Backend = "openvino",
    precision: Precision = "f32",
    threads: int = 1,
) -> _Predictor:
    """A predictor for ``model`` usable by ``rollout`` in place of it (module docstring).

    Args:
        model: a surrogate in eval mode (NEMSim: ``precompute``/``step`` or ``predict``; others:
            ``forward(x (B, 2, D, H, W), u (B, 14))``).
        backend: "openvino" (falls back to "torch" with a logged reason when unavailable) or "torch".
        precision: "f32" or "bf16".
        threads: OpenVINO inference threads per request (torch: recorded only; set torch's yourself).
    Returns:
        TorchPredictor or OpenVINOPredictor; ``.backend`` is what runs, ``.fallback_reason`` why not openvino.
    """
    cfg = RuntimeConfig(backend=backend, precision=precision, threads=int(threads))
    model = model.eval()
    if cfg.backend == "openvino":
        if not openvino_available():
            reason = "openvino is not installed (pip install 'nemsim[fast]')"
        else:
            try:
                return OpenVINOPredictor(model, cfg.precision, cfg.threads)
            except Exception as exc:  # noqa: BLE001 -- any export failure falls back to the reference path
                reason = f"openvino export failed: {type(exc).__name__}: {_first_line(exc)}"
        log.warning("runtime: using torch instead of openvino: %s", reason)
        pred = TorchPredictor(model, cfg.precision, cfg.threads)
        pred.fallback_reason = reason
        return pred
    return TorchPredictor(model, cfg.precision, cfg.threads)

