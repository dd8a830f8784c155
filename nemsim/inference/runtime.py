"""Inference runtimes for a surrogate's step network: ``compile_model(model, backend, precision, threads)``.

A runtime has the model's inference API (``nemsim.inference.eager.Runtime``) and is accepted by
``nemsim.evaluation.rollout.rollout`` in place of the model. Backends:
  * ``"torch"``: PyTorch eager, the reference (``nemsim.inference.eager.TorchRuntime``); bf16 via autocast.
  * ``"openvino"``: the per-step part exported to OpenVINO's CPU plugin (the optional extra ``nemsim[fast]``);
    falls back to ``"torch"`` with a logged reason (``fallback_reason``) when unavailable or the export fails.
  * ``"cuda"``: the k-state call (or a whole constant-control rollout) captured in CUDA graphs
    (``nemsim.inference.cuda_graph``); eager torch when CUDA is unavailable.

What is exported (choice): ``step(x, cache)`` with the control-derived tensors of ``cache`` as graph inputs.
``precompute(u)`` stays in PyTorch fp32 (once per control vector; the rule kinetics are not bf16-friendly);
cache entries that differ between two random control vectors become inputs, the rest constants. For NEMSim
the graph ends at the decoder's packed residuals and the k states are written outside it by
``nemsim.model.unpack.write_states`` (one fused pass into the caller's buffer).
Shapes are static: one model is compiled per (state shape incl. batch, input shapes) on first use. Infer
requests come from a pool (one per concurrent call); outputs are copied out, never aliased.
Threads (choice): ``threads`` is OpenVINO's ``INFERENCE_NUM_THREADS`` with one stream and pinning off, default
1 (two concurrent 1-thread rollouts fill a 2-core machine); torch's thread count is the caller's.
Speed-ups per backend are measured by ``nemsim bench speed-error`` and ``nemsim bench rollout``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils import _pytree as pytree

from nemsim.controls import N_CONTROLS
from nemsim.inference.eager import (  # noqa: F401 -- re-exported: the runtime API in one place
    BACKENDS,
    Backend,
    Runtime,
    RuntimeConfig,
    TorchRuntime,
    _check_out,
    _first_line,
    model_precompute,
    model_predict,
)
from nemsim.inference.precision import PRECISIONS, Precision  # noqa: F401 -- re-exported
from nemsim.model.unpack import NO_FINISH, Finish, write_states

log = logging.getLogger(__name__)
_CORE: Any = None
_CORE_LOCK = threading.Lock()


def openvino_core() -> Any:
    """The process's one ``openvino.Core``, made on first use and kept: its CPU plugin is loaded once and
    never unloaded. With a Core per runtime the plugin library was loaded and unloaded as runtimes came and
    went while its worker threads lived on, and long test processes that made and dropped many runtimes
    crashed inside the dynamic loader; one Core rules that pattern out. A Core is safe to share between
    threads."""
    global _CORE
    with _CORE_LOCK:
        if _CORE is None:
            import openvino as ov

            _CORE = ov.Core()
        return _CORE


def openvino_available() -> bool:
    try:
        import openvino  # noqa: F401
    except ImportError:
        return False
    return True


@contextlib.contextmanager
def _export_kernels() -> Iterator[None]:
    """Swap eager-tuned kernels for standard ops with the same values while tracing for export: the layers'
    direct oneDNN calls (``aten.mkldnn_convolution``, prepacked weights: not convertible) become
    ``F.conv3d``, the decoder's broadcast-copy 2x up-sampling becomes ``F.interpolate(nearest)``
    (OpenVINO ran the 8-D broadcast as a slow element-wise multiply), and GroupNorm runs on a 4-D view
    (``_group_norm_4d``). Module globals are swapped for the
    duration of the trace (under the runtime's lock); an eager rollout running meanwhile in another
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


class _StepGraph(nn.Module):
    """predict(x, cache) with the cache's variable leaves as inputs and its constant leaves as buffers."""

    def __init__(self, model: nn.Module, spec: Any, leaves: list[Any], variable: list[int],
                 packed: bool = False) -> None:
        super().__init__()
        self.model = model
        self.spec = spec
        self.variable = variable
        self.leaves = list(leaves)  # constants in place; the variable slots are replaced per call
        self.packed = packed  # output the decoder's packed residuals instead of the k states

    def forward(self, x: torch.Tensor, *inputs: torch.Tensor) -> torch.Tensor:
        leaves = list(self.leaves)
        for i, t in zip(self.variable, inputs, strict=True):
            leaves[i] = t
        cache = pytree.tree_unflatten(leaves, self.spec)
        if self.packed:
            return self.model.predict_packed(x, cache)  # type: ignore[operator]  # (B, 16k, D'/2, H'/2, W'/2)
        return model_predict(self.model, x, cache)  # (B, k, 2, D, H, W)


@dataclass
class _OVCache:
    """What ``OpenVINORuntime.precompute`` returns: the control-derived graph inputs as numpy arrays."""

    inputs: list[Any]  # numpy arrays, order of the graph's inputs after x
    batch: int
    torch_cache: Any  # the model's own cache (used if the export fails and the runtime falls back)


class OpenVINORuntime(Runtime):
    """The step graph compiled by OpenVINO's CPU plugin (module docstring)."""

    backend = "openvino"
    # OpenVINO 2026.4's CPU plugin crashed (SIGSEGV in compile_model) on the f32 NEMSim step graph at batch
    # > 1 with its subgraph "snippets" on; disabling them fixed it (speed: module docstring).
    extra_properties: dict[str, Any] = {"SNIPPETS_MODE": "DISABLE"}
    fuse_depth_to_space = True  # ``_fuse_depth_to_space`` on the converted graph
    # a model with ``predict_packed`` (NEMSim) is exported up to the decoder's packed residuals and its k
    # states are formed by ``nemsim.model.unpack.write_states`` straight into the caller's buffer
    unpack_states = True

    def __init__(self, model: nn.Module, precision: str = "f32", threads: int = 1) -> None:
        import openvino as ov

        super().__init__(model)
        self.precision = precision
        self.threads = int(threads)
        self._ov = ov
        self._core = openvino_core()
        self._compiled: dict[tuple, Any] = {}
        self._lock = threading.Lock()
        self._idle: dict[tuple, list[Any]] = {}  # shape key -> infer requests not in use
        self._scratches: dict[int, Any] = {}  # id(request) -> its output scratch array (``_scratch``)
        self._fallback: TorchRuntime | None = None
        self._spec, self._variable = self._cache_layout()
        self._unpack = self.unpack_states and callable(getattr(model, "predict_packed", None))

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
        from openvino.frontend.pytorch.ts_decoder import TorchScriptPythonDecoder

        ov = self._ov
        # the tracer cannot record inference tensors (a caller under torch.inference_mode): plain copies
        with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the tracer's notes on shape checks are not the user's concern
            leaves, _ = pytree.tree_flatten(cache.torch_cache)
            leaves = [t.detach().clone() if isinstance(t, torch.Tensor) else t for t in leaves]
            graph = _StepGraph(self.model, self._spec, leaves, self._variable, self._unpack).eval()
            example = (x.detach().float().clone(), *(torch.from_numpy(a.copy()) for a in cache.inputs))
            with _export_kernels():
                # TorchScript trace without torch.jit.trace's self-check: the check re-runs the model
                # and imports torch.testing, which pulls in sympy (tens of MB resident for good)
                decoder = TorchScriptPythonDecoder(
                    graph, example_input=example, trace_kwargs={"check_trace": False}
                )
                ov_model = ov.convert_model(decoder, example_input=example)
            # the trace leaves every input dimension dynamic: fixing them lets the plugin fold the shape
            # arithmetic and plan memory and kernels once instead of on every call
            ov_model.reshape({i: ov.PartialShape([int(n) for n in t.shape]) for i, t in enumerate(example)})
            if self.fuse_depth_to_space and not self._unpack:
                _fuse_depth_to_space(ov_model)
            ov_model = self.transform(ov_model)
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

    def transform(self, ov_model: Any) -> Any:
        """The converted step graph (static shapes) as it goes to the CPU plugin: unchanged here; a
        subclass rewrites it (e.g. the int8 lever measured by ``nemsim bench rollout``)."""
        return ov_model

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
        # memory from torch's allocator, which reuses freed blocks: numpy's ``out.copy()`` maps fresh pages
        # for every multi-MB result (page faults cost several times the copy itself)
        res = torch.empty((x.shape[0], self.k, *x.shape[1:]), dtype=torch.float32)  # (B, k, 2, D, H, W)
        return self.predict_into(x, cache, res)

    def predict_into(self, x: torch.Tensor, cache: Any, out: torch.Tensor,
                     finish: Finish = NO_FINISH) -> torch.Tensor:
        """The first n = out.shape[1] <= k states copied straight from the request's output buffer into out
        (B, n, 2, D, H, W): no intermediate copy; x is read in place when it is contiguous float32. Then
        ``finish``ed: in the same pass where the graph's output is the decoder's packed residuals."""
        if not isinstance(cache, _OVCache):
            raise TypeError(f"cache must come from this runtime's precompute(), got {type(cache).__name__}")
        if x.shape[0] != cache.batch:
            raise ValueError(f"the cache holds controls for batch {cache.batch}, x has batch {x.shape[0]}")
        _check_out(out, x, self.k)
        n = out.shape[1]
        if self._fallback is not None:
            out.copy_(self._fallback.predict(x, cache.torch_cache)[:, :n])
            return finish.apply_(out)
        try:
            key, req = self._acquire(x, cache)
        except Exception as exc:  # noqa: BLE001 -- an export failure falls back to the reference path
            self.fallback_reason = f"openvino export failed: {type(exc).__name__}: {_first_line(exc)}"
            log.warning("runtime: using torch instead of openvino: %s", self.fallback_reason)
            self._fallback = TorchRuntime(self.model, self.precision, self.threads)
            self.backend = "torch"
            out.copy_(self._fallback.predict(x, cache.torch_cache)[:, :n])
            return finish.apply_(out)
        try:
            if self._unpack:
                return self._infer_packed(req, x, cache, out, finish)
            ov = self._ov
            # inputs and output are the caller's memory (no copies by the Python bindings): x as it is when
            # contiguous float32 (the rollout's buffer), out when it takes all k states contiguously
            # (the rollout's trajectory buffer at batch 1), else the request's own scratch and one copy
            direct = n == self.k and out.dtype == torch.float32 and out.is_contiguous()
            dst = out.detach().numpy() if direct else self._scratch(req, out.shape[0])  # (B, k, 2, D, H, W)
            # a shared ov.Tensor does not keep its array alive: xin is held until the call has returned
            xin = x.detach().float().contiguous().numpy()  # (B, 2, D, H, W)
            req.set_input_tensor(0, ov.Tensor(xin, shared_memory=True))
            for i, a in enumerate(cache.inputs, start=1):
                req.set_input_tensor(i, ov.Tensor(a, shared_memory=True))
            req.set_output_tensor(0, ov.Tensor(dst, shared_memory=True))
            req.start_async()
            req.wait()
            if not direct:
                out.detach().numpy()[...] = dst[:, :n]
            return finish.apply_(out)
        finally:
            self._release(key, req)

    def _infer_packed(self, req: Any, x: torch.Tensor, cache: _OVCache, out: torch.Tensor,
                      finish: Finish) -> torch.Tensor:
        """One call of a packed-residual graph: the states written into out by ``write_states`` (gate, + x,
        clamp and ``finish`` in one pass) from the request's own output buffer, while the request is held."""
        ov = self._ov
        xin = x.detach().float().contiguous()  # (B, 2, D, H, W), held until the call has returned
        req.set_input_tensor(0, ov.Tensor(xin.numpy(), shared_memory=True))
        for i, a in enumerate(cache.inputs, start=1):
            req.set_input_tensor(i, ov.Tensor(a, shared_memory=True))
        req.start_async()
        req.wait()
        r = torch.from_numpy(req.get_output_tensor(0).data).float()  # (B, 16k, D'/2, H'/2, W'/2)
        gate = cache.torch_cache.get("gate") if isinstance(cache.torch_cache, dict) else None
        return write_states(xin, r, gate, bool(getattr(self.config, "clamp_output", True)), out, finish)

    def describe(self) -> dict[str, Any]:
        """``Runtime.describe`` plus ``inference_precision``: what the CPU plugin runs the compiled graph in
        (it runs f32 under a bf16 hint on a CPU without AVX-512); None before the first compile."""
        with self._lock:
            compiled = next(iter(self._compiled.values()), None)
        ran = None if compiled is None else compiled.get_property("INFERENCE_PRECISION_HINT").get_type_name()
        return {**super().describe(), "inference_precision": ran}

    def _scratch(self, req: Any, batch: int) -> Any:
        """The request's own output array (B, k, 2, D, H, W) float32 for calls that keep fewer than k states
        or write to non-contiguous memory (made on first use, kept with the request)."""
        arr = self._scratches.get(id(req))
        if arr is None:
            shape = tuple(int(d) for d in req.get_output_tensor(0).shape)
            arr = self._scratches[id(req)] = torch.empty(shape, dtype=torch.float32).numpy()
        assert arr.shape[0] == batch
        return arr


def _fuse_depth_to_space(ov_model: Any) -> int:
    """Replace the decoder's voxel shuffle (``nemsim.model.decoder.depth_to_space``: Reshape to 8-D,
    Transpose (0, 1, 5, 2, 6, 3, 7, 4), Reshape back to 5-D) in a converted graph by OpenVINO's DepthToSpace
    (mode depth_first, block 2: the same index map, so the same values). The CPU plugin ran the 8-D
    Transpose with a generic kernel and a layout reorder before it; DepthToSpace has its own kernel on the
    plugin's blocked layouts. Returns the number of shuffles replaced."""
    import openvino.opset13 as ops

    replaced = 0
    for op in ov_model.get_ordered_ops():
        if op.get_type_name() != "Transpose":
            continue
        perm = op.input_value(1).get_node()
        pre = op.input_value(0).get_node()
        consumers = list(op.output(0).get_target_inputs())
        if (perm.get_type_name() != "Constant" or list(perm.get_vector()) != [0, 1, 5, 2, 6, 3, 7, 4]
                or pre.get_type_name() != "Reshape" or len(consumers) != 1
                or consumers[0].get_node().get_type_name() != "Reshape"):
            continue
        post = consumers[0].get_node()
        d2s = ops.depth_to_space(pre.input_value(0), "depth_first", 2)
        if d2s.get_output_partial_shape(0) != post.get_output_partial_shape(0):
            continue
        post.output(0).replace(d2s.output(0))
        replaced += 1
    ov_model.validate_nodes_and_infer_types()
    return replaced


def compile_model(
    model: nn.Module,
    backend: Backend = "openvino",
    precision: Precision = "f32",
    threads: int = 1,
) -> Runtime:
    """A runtime for ``model`` usable by ``rollout`` in place of it (module docstring).

    Args:
        model: a surrogate in eval mode (NEMSim: ``precompute``/``step`` or ``predict``; others:
            ``forward(x (B, 2, D, H, W), u (B, 14))``).
        backend: "openvino" (falls back to "torch" with a logged reason when unavailable) or "torch".
        precision: "f32" or "bf16".
        threads: OpenVINO inference threads per request (torch: recorded only; set torch's yourself).
    Returns:
        TorchRuntime or OpenVINORuntime; ``.backend`` is what runs, ``.fallback_reason`` why not openvino.
    """
    cfg = RuntimeConfig(backend=backend, precision=precision, threads=int(threads))
    model = model.eval()
    if cfg.backend == "cuda":  # CUDA graphs (nemsim.inference.cuda_graph); eager torch without CUDA
        from nemsim.inference.cuda_graph import cuda_runtime

        return cuda_runtime(model, cfg.precision, cfg.threads)
    if cfg.backend == "openvino":
        if not openvino_available():
            reason = "openvino is not installed (pip install 'nemsim[fast]')"
        else:
            try:
                return OpenVINORuntime(model, cfg.precision, cfg.threads)
            except Exception as exc:  # noqa: BLE001 -- any export failure falls back to the reference path
                reason = f"openvino export failed: {type(exc).__name__}: {_first_line(exc)}"
        log.warning("runtime: using torch instead of openvino: %s", reason)
        fallback = TorchRuntime(model, cfg.precision, cfg.threads)
        fallback.fallback_reason = reason
        return fallback
    return TorchRuntime(model, cfg.precision, cfg.threads)

