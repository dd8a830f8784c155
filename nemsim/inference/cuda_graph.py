"""CUDA-graph inference of a surrogate's k-state network call (``compile_model(model, "cuda")``).

On a GPU one call of a small model is a few hundred small kernels; eager PyTorch launches each of them from
Python, so at small batch sizes a call costs its launches, not its arithmetic. ``CUDAGraphRuntime``
captures the call ``predict(x, cache)`` once into a ``torch.cuda.CUDAGraph`` and then replays it: one launch
per call. It is a runtime (``nemsim.inference.runtime``: ``precompute``, ``predict``, ``predict_into``,
``step``, ``__call__``), so ``nemsim.evaluation.rollout.rollout`` runs it in place of the model, one replay
per network call; PyTorch eager (``TorchRuntime``) on the same device is the reference it is tested
against (tests/inference/test_cuda_graph.py).

How (the PyTorch CUDA-graph recipe):
  * static buffers: a graph replays on the memory it was captured with, so each graph owns its input state
    x (B, 2, D, H, W), a copy of every tensor of the control cache, and its output (B, k, 2, D, H, W). A call
    copies x into the static input, the cache's tensors into the static cache when the cache is not the one
    already loaded (once per control change in a rollout), replays, and copies the states out (straight
    into ``rollout``'s trajectory buffer through ``predict_into``).
  * one graph per (batch size, state shape), captured lazily on first use and kept: a rollout at batch 1
    and one at batch 64 capture twice. ``precompute(u)`` stays eager (once per control vector).
  * capture: a few warm-up calls on a side stream first (lazy cuBLAS/cuDNN initialization must not happen
    during capture), then ``torch.cuda.graph`` with ``capture_error_mode="thread_local"`` (a server's other
    threads may use the GPU meanwhile). Calls are serialized by a lock (the static buffers are shared) and
    run on the caller's current stream, ordered after the previous call's stream.
  * ``rollout(x0, u, steps)``: a whole constant-control rollout (every call, the monotone projection and
    the trajectory writes) captured as one graph per (batch, steps, state shape) and replayed with one
    launch; the same values as ``nemsim.evaluation.rollout.rollout`` with this runtime.
  * a model whose call cannot be captured (host synchronization inside, CPU tensors created per call)
    falls back to eager PyTorch on the GPU with a logged reason: ``backend`` then says "torch",
    ``fallback_reason`` why.

Without CUDA the runtime refuses to build (``CUDAUnavailable``); ``compile_model(model, "cuda")`` then
returns the eager ``TorchRuntime`` on the CPU with the reason in ``fallback_reason``.

Precision: "f32", or "bf16" under ``torch.autocast("cuda", bfloat16)`` (its weight cache off, as capture
requires); the rule side stays in fp32 as in eager. Measured speeds: ``python -m bench.gpu``.

Fused kernels (``fuse``, the default): the captured call is ``torch.compile``'s (Inductor's generated
kernels for the elementwise and reduction work around the convolutions), compiled once per input shape
and layout on first use (20-30 s on an H100 machine; ``Predictor.warm_up`` pays it before a service is
ready). A replay is bound by its kernel count, not its arithmetic, and fusing cut the 100-step `small`
rollout from 12.8 to 10.1 ms at batch 1 and from 0.46 to 0.34 ms per trajectory at batch 64 on one H100
(``benchmarks/gpu/rollout.md``). The fused kernels sum in another order: the states agree with eager to
float32 rounding (max |Δ| 5e-4 to 9e-4 over 100 steps, trajectory RMSE 2e-5), not bit for bit;
``fuse=False`` captures the eager kernels themselves (bit-identical to eager). A fused call that cannot be
compiled or captured (no Triton, say) is captured unfused, with the reason logged and kept in
``fuse_fallback_reason``. cuDNN's timed algorithm choice (``torch.backends.cudnn.benchmark``) changed
nothing at these sizes, and is left as configured.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn
from torch.utils import _pytree as pytree

from nemsim.inference.eager import (
    PRECISIONS,
    Runtime,
    TorchRuntime,
    _check_out,
    _first_line,
    model_precompute,
    model_predict,
)
from nemsim.model.unpack import NO_FINISH, Finish
from nemsim.symmetry import model_fold

log = logging.getLogger(__name__)

WARMUP_CALLS = 3  # eager calls on a side stream before capturing a call
WARMUP_ROLLOUTS = 1  # eager runs before capturing a whole rollout (each is steps / k calls)
_CAPTURE_LOCK = threading.Lock()  # one capture at a time in the process (a CUDA graph constraint)


@contextlib.contextmanager
def _plain_no_grad() -> Iterator[None]:
    """Outside inference mode (static buffers made here can be copied into from inside or outside one) and
    without autograd (``inference_mode(False)`` alone turns grad mode on)."""
    with torch.inference_mode(False), torch.no_grad():
        yield


class CUDAUnavailable(RuntimeError):
    """The CUDA graph backend was asked for where torch sees no CUDA device."""


def cuda_unavailable_reason() -> str | None:
    """Why CUDA graphs cannot run here, or None when they can."""
    if not torch.cuda.is_available():
        build = "a CPU-only torch build" if torch.version.cuda is None else "no visible CUDA device"
        return (f"CUDA is not available (torch.cuda.is_available() is False: {build}); use the 'torch' or "
                f"'openvino' backend on the CPU")
    return None


@dataclass
class GraphCache:
    """What ``CUDAGraphRuntime.precompute`` returns: the model's control cache on the GPU, flattened."""

    tree: Any  # the model's own cache (``model_precompute``), tensors on the runtime's device
    leaves: list[Any]  # its pytree leaves
    spec: Any  # its pytree structure
    batch: int


@dataclass
class _Graph:
    """One captured call (or rollout) and the static memory it replays on."""

    replay: Callable[[], None]
    x: torch.Tensor  # static input state (B, 2, D, H, W)
    leaves: list[Any]  # static cache leaves (tensors are copied into on load; others must be equal)
    spec: Any
    out: torch.Tensor  # static output: (B, k, 2, D, H, W) per call, (B, T + 1, 2, D, H, W) per rollout
    loaded: GraphCache | None = field(default=None)  # the cache whose values the static leaves hold
    # the captured function: it holds every tensor the graph reads or writes that was allocated before the
    # capture (e.g. the monotone projection's running maximum and slack field); freed, their memory would
    # be handed to other tensors while the replays still use it
    body: Callable[[], torch.Tensor] | None = field(default=None)


class CUDAGraphRuntime(Runtime):
    """The k-state network call replayed from CUDA graphs, one per batch size (module docstring).

    Args:
        model: a surrogate (NEMSim: ``precompute`` / ``predict``; others ``forward(x, u)``); it is moved to
            ``device`` (in place) and put in eval mode.
        precision: "f32" or "bf16" (CUDA autocast).
        threads: recorded only (the GPU does the work).
        device: a CUDA device; default: the model's if it is on one, else the current CUDA device.
        fuse: capture the call compiled by ``torch.compile`` (module docstring); False: the eager kernels.
    """

    backend = "cuda"

    def __init__(self, model: nn.Module, precision: str = "f32", threads: int = 1,
                 device: torch.device | str | None = None, *, fuse: bool = True) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"unknown precision {precision!r}; expected one of {PRECISIONS}")
        self.device = self._resolve_device(model, device)
        super().__init__(model.to(self.device).eval())
        self.precision = precision
        self.threads = int(threads)
        self.fuse = bool(fuse)
        self.fuse_fallback_reason: str | None = None
        self._call: Callable[[torch.Tensor, Any], torch.Tensor] = (
            torch.compile(self._model_call, dynamic=False) if self.fuse else self._model_call)
        self._lock = threading.RLock()
        self._graphs: dict[tuple, _Graph] = {}  # (B, state shape) -> the captured call
        self._rollouts: dict[tuple, _Graph] = {}  # (B, steps, state shape, monotone) -> the captured rollout
        self._eager = False  # a capture failed: every call runs eager (``fallback_reason``)
        self._stream: Any = None  # the stream of the last call (the next one is ordered after it)
        self._capture_stream: Any = None  # the stream graphs are captured on

    # -- device ----------------------------------------------------------------------------------------

    @staticmethod
    def _resolve_device(model: nn.Module, device: torch.device | str | None) -> torch.device:
        reason = cuda_unavailable_reason()
        if reason is not None:
            raise CUDAUnavailable(reason)
        if device is None:
            p = next(iter(model.parameters()), None)
            if p is not None and p.device.type == "cuda":
                return p.device
            return torch.device("cuda", torch.cuda.current_device())
        dev = torch.device(device)
        if dev.type != "cuda":
            raise ValueError(f"the CUDA graph backend runs on a CUDA device, got device {str(dev)!r}")
        return dev if dev.index is not None else torch.device("cuda", torch.cuda.current_device())

    def _ctx(self):
        return torch.autocast("cuda", dtype=torch.bfloat16, enabled=self.precision == "bf16",
                              cache_enabled=False)  # fmt: skip

    def _model_call(self, x: torch.Tensor, tree: Any) -> torch.Tensor:
        return model_predict(self.model, x, tree)  # (B, k, 2, D, H, W)

    def _capture(self, body: Callable[[], torch.Tensor],
                 warmup: int) -> tuple[Callable[[], None], torch.Tensor]:
        """(replay, static output) of ``body`` captured into a CUDA graph after ``warmup`` eager runs on a
        side stream. ``body`` reads and writes only the static buffers and returns its output."""
        current = torch.cuda.current_stream(self.device)
        side = torch.cuda.Stream(self.device)
        side.wait_stream(current)
        with torch.cuda.stream(side):
            for _ in range(warmup):
                body()
        current.wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        pool = torch.cuda.graph_pool_handle()  # the graph's own pool, named: a failure must release it
        if self._capture_stream is None:
            self._capture_stream = torch.cuda.Stream(self.device)
        with _CAPTURE_LOCK:
            try:
                with torch.cuda.graph(graph, pool=pool, stream=self._capture_stream,
                                      capture_error_mode="thread_local"):
                    out = body()
            except BaseException:
                torch.cuda.set_stream(current)  # a failed capture_end leaves the capture stream current
                _release_failed_capture(self.device, pool)
                with contextlib.suppress(Exception):  # reads (and clears) an error left by the capture
                    torch.cuda.synchronize(self.device)
                raise
        return graph.replay, out

    @contextlib.contextmanager
    def _on_device(self) -> Iterator[None]:
        """The runtime's lock and CUDA device; the caller's current stream waits for the last call's work
        (calls may come from different streams, and they share the static buffers)."""
        with self._lock, torch.cuda.device(self.device):
            stream = torch.cuda.current_stream(self.device)
            if self._stream is not None and self._stream != stream:
                stream.wait_stream(self._stream)
            self._stream = stream
            yield

    # -- the runtime API -----------------------------------------------------------------------------------

    @torch.no_grad()
    def precompute(self, u: torch.Tensor) -> GraphCache:
        with self._on_device():  # eager and fp32, as the reference runtime's
            tree = model_precompute(self.model, u.to(self.device, torch.float32))
        leaves, spec = pytree.tree_flatten(tree)
        return GraphCache(tree, leaves, spec, int(u.shape[0]))

    def predict(self, x: torch.Tensor, cache: Any) -> torch.Tensor:
        """The next k states (B, k, 2, D, H, W) float32 on x's device (a fresh tensor)."""
        out = torch.empty((x.shape[0], self.k, *x.shape[1:]), dtype=torch.float32, device=x.device)
        return self.predict_into(x, cache, out)

    @torch.no_grad()
    def predict_into(self, x: torch.Tensor, cache: Any, out: torch.Tensor,
                     finish: Finish = NO_FINISH) -> torch.Tensor:
        """The first n = out.shape[1] <= k states written into out (B, n, 2, D, H, W) (any device): copy x
        into the graph's static input, replay, copy the states out; then ``finish`` them (on the device, a
        few kernels per call)."""
        return finish.apply_(self._write_into(x, cache, out))

    def _write_into(self, x: torch.Tensor, cache: Any, out: torch.Tensor) -> torch.Tensor:
        cache = self._as_cache(cache, x)
        _check_out(out, x, self.k)
        n = out.shape[1]
        with self._on_device():
            if self._eager:
                return out.copy_(self._eager_predict(x, cache)[:, :n])
            key = (int(x.shape[0]), tuple(int(d) for d in x.shape[1:]))
            graph = self._graphs.get(key)
            if graph is None:
                graph = self._capture_call(x, cache, key)
                if graph is None:  # the capture failed: eager from now on
                    return out.copy_(self._eager_predict(x, cache)[:, :n])
            self._load(graph, cache)
            graph.x.copy_(x)
            graph.replay()
            return out.copy_(graph.out[:, :n])

    def _as_cache(self, cache: Any, x: torch.Tensor) -> GraphCache:
        if not isinstance(cache, GraphCache):  # the model's own cache dict: flatten it here
            leaves, spec = pytree.tree_flatten(cache)
            tensors = [t for t in leaves if isinstance(t, torch.Tensor) and t.dim() > 0]
            cache = GraphCache(cache, leaves, spec, int(tensors[0].shape[0]) if tensors else int(x.shape[0]))
        if x.dim() != 5 or x.shape[0] != cache.batch:
            raise ValueError(f"x must be (B, 2, D, H, W) with B = {cache.batch} (the cache's batch), "
                             f"got {tuple(x.shape)}")
        return cache

    def _eager_predict(self, x: torch.Tensor, cache: GraphCache) -> torch.Tensor:
        with self._ctx():
            return model_predict(self.model, x.to(self.device, torch.float32), cache.tree).float()

    def _static_like(self, x: torch.Tensor, cache: GraphCache) -> tuple[torch.Tensor, list[Any]]:
        """Static input and cache leaves for a capture, holding the values of x and cache. Made outside any
        inference mode, so that later calls (inside or outside one) may copy into them."""
        with _plain_no_grad():
            sx = torch.empty(x.shape, dtype=torch.float32, device=self.device)  # (B, 2, D, H, W)
            sx.copy_(x)
            leaves = [t.detach().to(self.device).clone() if isinstance(t, torch.Tensor) else t
                      for t in cache.leaves]  # fmt: skip
        return sx, leaves

    def _capture_call(self, x: torch.Tensor, cache: GraphCache, key: tuple) -> _Graph | None:
        sx, leaves = self._static_like(x, cache)
        tree = pytree.tree_unflatten(leaves, cache.spec)

        def body() -> torch.Tensor:
            with self._ctx():
                return self._call(sx, tree).float()  # (B, k, 2, D, H, W)

        graph = self._try_capture(body, WARMUP_CALLS, f"the call at batch {key[0]}", sx, leaves, cache)
        if graph is not None:
            self._graphs[key] = graph
        return graph

    def _try_capture(self, body: Callable[[], torch.Tensor], warmup: int, what: str, sx: torch.Tensor,
                     leaves: list[Any], cache: GraphCache) -> _Graph | None:
        """The captured graph of ``body``, or None (eager from now on, ``fallback_reason`` set)."""
        try:
            with _plain_no_grad():
                replay, out = self._capture(body, warmup)
        except Exception as exc:  # noqa: BLE001 -- an uncapturable model runs eager, with the reason logged
            if self.fuse:  # the fused call failed to compile or capture: capture the eager kernels instead
                self.fuse_fallback_reason = f"{type(exc).__name__}: {_first_line(exc)}"
                log.warning("cuda graph: capturing the unfused call on %s: the fused one failed: %s",
                            self.device, self.fuse_fallback_reason)
                self.fuse, self._call = False, self._model_call
                return self._try_capture(body, warmup, what, sx, leaves, cache)
            self.fallback_reason = f"CUDA graph capture failed: {type(exc).__name__}: {_first_line(exc)}"
            log.warning("runtime: eager torch on %s instead of a CUDA graph: %s", self.device,
                        self.fallback_reason)
            self._eager = True
            self.backend = "torch"
            return None
        log.info("cuda graph: captured %s, state %s (%s)", what, tuple(sx.shape[1:]), self.precision)
        return _Graph(replay, sx, leaves, cache.spec, out, loaded=cache, body=body)

    def _load(self, graph: _Graph, cache: GraphCache) -> None:
        """Copy the cache's tensors into the graph's static leaves unless they hold this cache already."""
        if graph.loaded is cache:
            return
        if cache.spec != graph.spec:
            raise ValueError("precompute(u) changed structure since the capture; build a new runtime")
        for dst, src in zip(graph.leaves, cache.leaves, strict=True):
            if isinstance(dst, torch.Tensor):
                if dst.shape != src.shape:
                    raise ValueError(f"a cache tensor of shape {tuple(src.shape)} does not fit the captured "
                                     f"{tuple(dst.shape)}")
                dst.copy_(src)
            elif dst != src:
                raise ValueError(f"a non-tensor cache entry changed since the capture ({dst!r} -> {src!r}); "
                                 "it is part of the captured graph")
        graph.loaded = cache

    # -- whole rollouts ------------------------------------------------------------------------------------

    @torch.no_grad()
    def rollout(self, x0: torch.Tensor, u: torch.Tensor, steps: int, *, monotone: bool | None = None,
                copy: bool = True) -> torch.Tensor:
        """A constant-control rollout of ``steps`` transitions replayed as one graph (module docstring):
        (B, steps + 1, 2, D, H, W) float32 on the runtime's device, x0 first; the values of
        ``nemsim.evaluation.rollout.rollout(self, x0, u, steps, monotone=monotone)``.

        Args:
            x0: (B, 2, D, H, W) initial states.
            u: (B, 14) normalized controls, constant over the rollout (a recipe: use ``rollout`` of
                ``nemsim.evaluation.rollout`` with this runtime).
            steps: transitions.
            monotone: the rollout's monotone projection (None: the model's default).
            copy: return a fresh tensor; False returns the graph's static trajectory buffer, overwritten by
                the next rollout of the same shape.
        """
        if x0.dim() != 5 or u.dim() != 2 or u.shape[0] != x0.shape[0]:
            raise ValueError(f"x0 must be (B, 2, D, H, W) and u (B, 14) constant controls, got "
                             f"{tuple(x0.shape)} and {tuple(u.shape)}")
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        f = model_fold(self)
        if f is not None and f.is_full(x0):  # a quarter- or section-domain model: the graph runs folded
            from nemsim.evaluation.rollout import on_quadrant

            return on_quadrant(x0.to(self.device, torch.float32), f,
                               lambda xq: self.rollout(xq, u, steps, monotone=monotone, copy=copy))
        cache = self.precompute(u)
        with self._on_device():
            key = (int(x0.shape[0]), int(steps), tuple(int(d) for d in x0.shape[1:]), monotone)
            graph = None if self._eager else self._rollouts.get(key)
            if graph is None and not self._eager:
                graph = self._capture_rollout(x0, cache, steps, monotone, key)
            if graph is None:  # eager: the library's rollout with this (now eager) runtime
                from nemsim.evaluation.rollout import rollout

                x0 = x0.to(self.device, torch.float32)
                return rollout(self, x0, u, steps, monotone=monotone)  # type: ignore[arg-type]
            self._load(graph, cache)
            graph.x.copy_(x0)
            graph.replay()
            return graph.out.clone() if copy else graph.out

    def _capture_rollout(self, x0: torch.Tensor, cache: GraphCache, steps: int, monotone: bool | None,
                         key: tuple) -> _Graph | None:
        from nemsim.model.monotone import projection_of

        sx, leaves = self._static_like(x0, cache)
        tree = pytree.tree_unflatten(leaves, cache.spec)
        with _plain_no_grad():
            traj = torch.empty((sx.shape[0], steps + 1, *sx.shape[1:]), dtype=torch.float32,
                               device=self.device)  # (B, T + 1, 2, D, H, W)
            project = projection_of(self.model, sx, monotone)  # its slack field is made here, not captured
        k = self.k

        def body() -> torch.Tensor:
            """``nemsim.evaluation.rollout.rollout`` with constant controls: chunks of min(k, steps left)."""
            traj[:, 0].copy_(sx)
            if project is not None:
                project.running_max.copy_(sx)
            x, t = sx, 0
            while t < steps:
                n = min(k, steps - t)
                with self._ctx():
                    states = self._call(x, tree)  # (B, k, 2, D, H, W)
                dst = traj[:, t + 1 : t + 1 + n]
                dst.copy_(states[:, :n])
                if project is not None:
                    project.project_chunk_(dst)
                x = dst[:, n - 1]  # (B, 2, D, H, W)
                t += n
            return traj

        graph = self._try_capture(body, WARMUP_ROLLOUTS, f"a {steps}-step rollout at batch {key[0]}", sx,
                                  leaves, cache)
        if graph is not None:
            self._rollouts[key] = graph
        return graph

    def describe(self) -> dict[str, Any]:
        return {**super().describe(), "device": str(self.device), "fuse": self.fuse,
                **({"fuse_fallback_reason": self.fuse_fallback_reason} if self.fuse_fallback_reason else {}),
                "graphs": sorted(b for b, _ in self._graphs),
                "rollout_graphs": sorted((b, t) for b, t, _, _ in self._rollouts)}  # fmt: skip


def _release_failed_capture(device: torch.device, pool: Any) -> None:
    """After a failed capture, the allocator bookkeeping that a successful ``capture_end`` does: stop
    routing allocations to the graph's pool and release it. Without it the allocator keeps the capture
    listed as underway, and the next ``torch.cuda.empty_cache()`` (every later capture starts with one)
    fails an internal assertion. A capture whose ``capture_end`` succeeded (the error was raised by Python
    code inside it) is no longer listed: ending it raises, and the graph releases its pool itself.
    Best effort, through PyTorch's private allocator bindings (the names of recent releases)."""
    end = getattr(torch._C, "_cuda_endAllocateToPool", None) or getattr(
        torch._C, "_cuda_endAllocateCurrentStreamToPool", None)
    release = getattr(torch._C, "_cuda_releasePool", None)
    if end is None or release is None:
        log.warning("cuda graph: cannot release the pool of a failed capture (torch %s)", torch.__version__)
        return
    index = device.index if device.index is not None else torch.cuda.current_device()
    try:
        end(index, pool)
    except Exception:  # noqa: BLE001 -- capture_end ran: not underway, and the graph owns its pool
        return
    try:
        release(index, pool)
    except Exception as exc:  # noqa: BLE001 -- keep the capture's own error, which is the one to report
        log.warning("cuda graph: releasing the pool of a failed capture: %s", _first_line(exc))


def cuda_runtime(model: nn.Module, precision: str = "f32", threads: int = 1) -> Runtime:
    """``compile_model(model, "cuda")``: a ``CUDAGraphRuntime``, or, without CUDA, the eager
    ``TorchRuntime`` on the CPU with the reason in ``fallback_reason`` (logged)."""
    reason = cuda_unavailable_reason()
    if reason is None:
        return CUDAGraphRuntime(model, precision, threads)
    log.warning("runtime: using torch on the CPU instead of CUDA graphs: %s", reason)
    fallback = TorchRuntime(model.eval(), precision, threads)
    fallback.fallback_reason = reason
    return fallback
