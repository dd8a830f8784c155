"""The served model: a `nemsim.inference.Predictor` plus what a server needs around it.

No physics here: rollouts, profile metrics and meshes are the predictor's, mechanisms
`nemsim.analysis.counterfactual.mechanism_response`. This module adds:

* a model id (checkpoint stem + the first 12 hex digits of the file's SHA-256);
* an LRU cache of finished rollouts keyed by (model id, feature as built, normalized controls per
  transition, steps); the
  key's hash is the rollout id, so a repeat, a follow-up mesh request or a request giving the same
  controls normalized recomputes nothing. States are kept as float16 (what the API returns anyway),
  stored compactly and losslessly (`service.compact_states`), so the entry count, not the memory budget,
  bounds the cache: the ids of the last `cache_size` rollouts answered always resolve (while they fit in
  the budget), and rollouts followed up or repeated outlive a flood of one-off ones (`_LRU`);
* reused trajectory buffers (a fresh trajectory-sized array per rollout costs page faults);
* the compact cache entry is encoded after the answer: a rollout's metrics are ready before its states are
  stored, so `compute_rollout` returns with them, and one worker thread rounds the states to float16 and
  encodes them while the response goes out (about a sixth of an uncached `POST /rollout` on `small`),
  then gives the trajectory buffer back. Until then the rollout is pending: its id resolves, and whatever
  reads its states (`RolloutResult.states`: fields, meshes, comparisons) waits for the encoding;
* cache look-ups apart from computations (`lookup_rollout` / `compute_rollout`, `cached_mesh` / `mesh`,
  `cached_mechanisms` / `mechanisms`), so the app answers cache hits on the event loop and admits the
  computations through its own gates (`service.scheduler`). This class does no admission control.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import threading
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nemsim.inference import ControlSchedule, Predictor
from nemsim.symmetry import FieldFold
from service.compact_states import CompactStates
from service.schemas import array_to_controls, jsonable

log = logging.getLogger(__name__)


class UnknownRollout(KeyError):
    """No cached rollout has this id (never computed here, or evicted)."""


@dataclass(frozen=True)
class RolloutResult:
    id: str
    model_id: str
    steps: int
    controls_raw: np.ndarray  # (T, 14) physical units
    encoded: Future[CompactStates]  # the states being stored (`states` waits for them)
    metrics: dict[str, list[float | None]]  # name -> (T+1,) values in nm, None where undefined
    times_s: list[float]  # (T+1,)
    rollout_ms: float
    metrics_ms: float
    warnings: tuple[str, ...] = ()  # stability guard findings (non-finite or out-of-range states)
    non_finite_from: int | None = None  # the first step whose state is not finite, None: all finite
    case: Any = None  # the predictor's FeatureCase rolled out (feature, per-case scene, x0)

    @property
    def scene(self) -> Any:
        """The per-case scene of this rollout (its frame, the metrics' rows)."""
        return self.case.scene

    @property
    def geometry(self) -> dict[str, Any]:
        """The feature rolled out, as built on the grid ({kind, cd_nm, mask_nm})."""
        return dict(self.case.feature.to_dict())

    @property
    def states(self) -> CompactStates:
        """The states (T+1, 2, D, H, W) float16, normalized SDF, stored compactly (waits for the encoding)."""
        return self.encoded.result()


class _LRU:
    """Least-recently-used cache: the `size` most recently used keys always stay (a plain LRU), and on top
    up to `size` * `KEPT_SHARE` keys that fell out of it after being used again (a hit) stay longer, so a
    stream of one-off entries cannot flush the entries clients come back to. `get(key, touch=False)` is a
    follow-up look-up: it counts as a use again (the entry will be kept) without making the entry one of the
    most recent, so follow-ups of old entries never push recent ones out. With `weigh`, both together are
    bounded by `max_bytes` (the kept ones are evicted first; an entry larger than the whole budget is not
    kept); the guarantee on the `size` most recent holds while they fit in the budget."""

    KEPT_SHARE = 0.5

    def __init__(
        self, size: int, max_bytes: int | None = None, weigh: Callable[[Any], int] | None = None
    ) -> None:
        self.size = size
        self.kept_size = int(size * self.KEPT_SHARE)
        self.max_bytes = max_bytes
        self.weigh = weigh or (lambda value: 0)
        self.bytes = 0  # both segments
        self._recent: OrderedDict[Any, tuple[Any, int, bool]] = OrderedDict()  # (value, weight, hit?)
        self._kept: OrderedDict[Any, tuple[Any, int]] = OrderedDict()  # (value, weight)
        self._lock = threading.Lock()

    def get(self, key: Any, *, touch: bool = True) -> Any | None:
        with self._lock:
            if key in self._recent:
                value, weight, _ = self._recent[key]
                self._recent[key] = (value, weight, True)
                if touch:
                    self._recent.move_to_end(key)
                return value
            if key not in self._kept:
                return None
            if not touch:
                self._kept.move_to_end(key)
                return self._kept[key][0]
            value, weight = self._kept.pop(key)
            self._recent[key] = (value, weight, True)
            self._shrink()
            return value

    def put(self, key: Any, value: Any, weight: int | None = None) -> None:
        """Keep `value` under `key`; `weight`: its bytes (default: `weigh(value)`)."""
        weight = self.weigh(value) if weight is None else weight
        if self.size <= 0 or (self.max_bytes is not None and weight > self.max_bytes):
            return
        with self._lock:
            hit = False
            if key in self._recent:
                _, old, hit = self._recent.pop(key)
                self.bytes -= old
            elif key in self._kept:
                self.bytes -= self._kept.pop(key)[1]
                hit = True
            self._recent[key] = (value, weight, hit)
            self.bytes += weight
            self._shrink()

    def _shrink(self) -> None:
        while len(self._recent) > self.size:
            key, (value, weight, hit) = self._recent.popitem(last=False)
            if hit and self.kept_size > 0:
                self._kept[key] = (value, weight)
            else:
                self.bytes -= weight
        while len(self._kept) > self.kept_size:
            self.bytes -= self._kept.popitem(last=False)[1][1]
        while self.max_bytes is not None and self.bytes > self.max_bytes:
            if self._kept:
                self.bytes -= self._kept.popitem(last=False)[1][1]
            else:
                self.bytes -= self._recent.popitem(last=False)[1][1]

    def __len__(self) -> int:
        return len(self._recent) + len(self._kept)


class ServedModel:
    """The predictor of the served checkpoint plus caches and trajectory buffers. Thread-safe."""

    def __init__(self, predictor: Predictor, *, cache_size: int = 32, cache_bytes: int | None = None) -> None:
        self.predictor = predictor
        self.model_id = predictor.model_id
        # cache_bytes: the budget of the rollout cache (the compact states dominate); meshes get a quarter
        # of it on top
        self._rollouts = _LRU(cache_size, cache_bytes)  # weighed by the compact states' bytes (`_store`)
        self._meshes = _LRU(4 * cache_size, None if cache_bytes is None else cache_bytes // 4, len)
        self._mechanisms = _LRU(cache_size)
        self._buffers: list[torch.Tensor] = []  # idle trajectory buffers (`_take_buffer`)
        self._buffers_lock = threading.Lock()
        # rollouts answered whose states are still being encoded (module docstring): id -> result
        self._pending: dict[str, RolloutResult] = {}
        self._encoder = ThreadPoolExecutor(1, thread_name_prefix="nemsim-encode")

    @classmethod
    def from_checkpoint(
        cls,
        path: str | Path,
        *,
        scene: str | None = None,
        cache_size: int = 32,
        cache_bytes: int | None = None,
        runtime_backend: str = "openvino",
        runtime_precision: str = "auto",
        runtime_threads: int = 1,
    ) -> ServedModel:
        """Load `path` weights-only (`nemsim.inference`; CheckpointError) and serve it; `scene`: the scene
        the checkpoint must be of (None: any). Rollouts run through the fast CPU runtime (PyTorch eager
        when openvino is missing, logged)."""
        predictor = Predictor.from_checkpoint(
            path, scene=scene, backend=runtime_backend, precision=runtime_precision, threads=runtime_threads
        )
        return cls(predictor, cache_size=cache_size, cache_bytes=cache_bytes)

    @property
    def scene(self) -> Any:
        return self.predictor.scene

    # --- rollouts ---------------------------------------------------------------------------------
    def rollout_id(self, schedule: ControlSchedule, case: Any = None) -> str:
        """The cache key's hash: model id, feature as built (`case`, None: the model's own), steps and
        controls."""
        feature = (case or self.predictor.case(None)).feature
        h = hashlib.sha256(self.model_id.encode())
        h.update(json.dumps(feature.to_dict(), sort_keys=True).encode())
        h.update(str(schedule.steps).encode())
        h.update(np.ascontiguousarray(schedule.normalized, dtype="<f4").tobytes())
        return h.hexdigest()[:24]

    def get_rollout(self, rollout_id: str) -> RolloutResult:
        """A cached rollout by id, for a follow-up request (mesh, slices): the rollout counts as used again
        (it outlives one-off rollouts) but does not become one of the `cache_size` most recent, so
        follow-ups of old rollouts never evict the ids of the latest POST /rollout answers."""
        result = self._find(rollout_id, touch=False)
        if result is None:
            raise UnknownRollout(rollout_id)
        return result

    def lookup_rollout(
        self, controls: ControlSchedule | np.ndarray, case: Any = None
    ) -> tuple[str, RolloutResult | None]:
        """(rollout id, the cached result or None) of a schedule or (T, 14) physical controls on `case`
        (the predictor's FeatureCase; None: the model's own feature)."""
        rid = self.rollout_id(self.predictor.schedule(controls), case)
        return rid, self._find(rid)

    def _find(self, rid: str, *, touch: bool = True) -> RolloutResult | None:
        """The rollout `rid` if cached or pending (answered, its states still being stored), else None."""
        return self._rollouts.get(rid, touch=touch) or self._pending.get(rid)

    def compute_rollout(
        self, controls: ControlSchedule | np.ndarray, rollout_id: str | None = None, case: Any = None
    ) -> tuple[RolloutResult, bool]:
        """Roll out and cache a schedule (blocking) on `case` (None: the model's own feature); `rollout_id`:
        its id when `lookup_rollout` gave it already. Returns (result, served_from_cache): an identical
        request may have finished while this one waited for a slot."""
        schedule = self.predictor.schedule(controls)
        case = case or self.predictor.case(None)
        rid = rollout_id or self.rollout_id(schedule, case)
        cached = self._find(rid)
        if cached is not None:
            return cached, True
        return self._compute(rid, schedule, case), False

    def _store(self, result: RolloutResult, buf: torch.Tensor, fold: FieldFold | None) -> None:
        """On the encoder thread: encode a pending rollout's states (its first steps + 1 of the trajectory
        buffer `buf`, float32, rounded to float16 on the way), give the buffer back, put the rollout in the
        cache, then resolve `result.encoded` (so whoever waited on it finds the rollout cached). A failed
        encoding is logged and the rollout forgotten; reading its states raises the error."""
        try:
            try:
                compact = CompactStates.encode(buf[: result.steps + 1], full_size=fold.n if fold else None,
                                               fold_kind=fold.kind if fold else "quarter")
            finally:
                self._give_back(buf)
        except BaseException as exc:
            log.error("rollout %s: storing its states failed: %r", result.id, exc)
            self._pending.pop(result.id, None)
            result.encoded.set_exception(exc)
            return
        self._rollouts.put(result.id, result, weight=compact.nbytes)
        self._pending.pop(result.id, None)
        result.encoded.set_result(compact)

    def rollout(self, controls: ControlSchedule | np.ndarray, case: Any = None) -> tuple[RolloutResult, bool]:
        """Cached or computed rollout on `case` (None: the model's own feature; blocking; no admission
        control)."""
        schedule = self.predictor.schedule(controls)
        rid, cached = self.lookup_rollout(schedule, case)
        return (cached, True) if cached is not None else self.compute_rollout(schedule, rid, case)

    def _compute(self, rid: str, schedule: ControlSchedule, case: Any) -> RolloutResult:
        buf = self._take_buffer(schedule.steps)  # (>= T+1, 2, D, H, W) float32, or the quadrant's shape
        try:  # a symmetric model's rollout stays on the quadrant (what the cache keeps; a quarter the work)
            pred = self.predictor.rollout(schedule, out=buf, quadrant=True, feature=case.feature)
            metrics = {
                k: [v if math.isfinite(v) else None for v in vals.tolist()]  # undefined (NaN): null
                for k, vals in pred.metrics.items()
            }
        except BaseException:
            self._give_back(buf)
            raise
        if pred.warnings:
            log.warning("rollout %s: %s", rid, "; ".join(pred.warnings))
        result = RolloutResult(
            id=rid,
            model_id=self.model_id,
            steps=schedule.steps,
            controls_raw=schedule.raw,
            encoded=Future(),
            metrics=metrics,
            times_s=pred.times_s,
            rollout_ms=1e3 * pred.rollout_s,
            metrics_ms=1e3 * pred.metrics_s,
            warnings=pred.warnings,
            non_finite_from=pred.non_finite_from,
            case=case,
        )
        self._pending[rid] = result  # answered now, cached once its states are stored (`_store`)
        self._encoder.submit(self._store, result, buf, pred.fold)  # the buffer is its until encoded
        return result

    def _take_buffer(self, steps: int) -> torch.Tensor:
        """A float32 trajectory buffer of at least steps + 1 states, reused across rollouts: a fresh
        array of a trajectory's size costs page faults on every rollout, and the stacked copy of the
        states another one. One buffer per rollout computing at the same time (`_give_back`)."""
        with self._buffers_lock:
            for i, buf in enumerate(self._buffers):
                if buf.shape[0] >= steps + 1:
                    return self._buffers.pop(i)
            if self._buffers:
                self._buffers.pop(0)  # too short for this rollout: replaced by a longer one
        with torch.inference_mode(False):
            return torch.empty((steps + 1, *self.predictor.state_shape(quadrant=True)), dtype=torch.float32)

    def _give_back(self, buf: torch.Tensor) -> None:
        with self._buffers_lock:
            self._buffers.append(buf)

    def warm_up(self, steps: int) -> None:
        """One short uncached rollout so the first request does not pay for allocation/JIT (the compact
        store's kernels included)."""
        self.predictor.warm_up(steps)
        if steps > 0:
            CompactStates.encode(torch.from_numpy(np.stack([self.predictor.x0] * 2))).decode()

    # --- meshes -------------------------------------------------------------------------------------
    def warm_up_meshes(self, formats: tuple[str, ...] = ("glb", "ply", "obj", "stl")) -> None:
        """Extract and export the initial Si surface once per format, so the first mesh request does not
        pay for imports and first-call compilation."""
        for fmt in formats:
            self.predictor.mesh(self.predictor.x0[1], fmt, {"warm_up": True})

    def cached_mesh(self, result: RolloutResult, step: int, channel: str, fmt: str) -> bytes | None:
        return self._meshes.get((result.id, step, channel, fmt))

    def mesh(self, result: RolloutResult, step: int, channel: str, fmt: str) -> bytes:
        """File bytes of the zero-level surface of one channel at one step (cached; blocking)."""
        key = (result.id, step, channel, fmt)
        data = self._meshes.get(key)
        if data is not None:
            return data
        ch = 0 if channel == "mask" else 1
        metadata = {
            "model_id": self.model_id,
            "rollout_id": result.id,
            "step": step,
            "time_s": result.times_s[step],
            "channel": channel,
            "scene": self.scene.name,
            "geometry": result.geometry,
            "controls": array_to_controls(result.controls_raw[max(step - 1, 0)]),
        }
        field = result.states.state(step)[ch].astype(np.float32)  # (D, H, W)
        data = self.predictor.mesh(field, fmt, metadata, scene=result.scene)
        self._meshes.put(key, data)
        return data

    # --- mechanisms ---------------------------------------------------------------------------------
    def _mechanisms_key(
        self, controls_raw: np.ndarray, factors: list[float] | None, case: Any = None
    ) -> tuple[bytes, Any, Any]:
        feature = (case or self.predictor.case(None)).feature
        if not factors:
            return np.asarray(controls_raw, dtype="<f8").tobytes(), None, feature
        levels = sorted({1.0, *map(float, factors)})
        pairs = tuple((a, b) for a in levels for b in levels if (a, b) != (1.0, 1.0))
        return np.asarray(controls_raw, dtype="<f8").tobytes(), pairs, feature

    def cached_mechanisms(
        self, controls_raw: np.ndarray, factors: list[float] | None, case: Any = None
    ) -> dict[str, Any] | None:
        return self._mechanisms.get(self._mechanisms_key(controls_raw, factors, case))

    def mechanisms(
        self, controls_raw: np.ndarray, factors: list[float] | None, case: Any = None
    ) -> dict[str, Any]:
        """`nemsim.analysis.counterfactual.mechanism_response` for one base control vector (14,) physical
        units from the predictor's initial state (cached), JSON-ready (`schemas.jsonable`: plain lists and
        floats, non-finite as None), so a cache hit costs no conversion.

        `factors` are flux multiplier levels; the interventions are every (s_Cl+, s_Cl) pair of the levels
        and 1, except (1, 1) -- {0.5, 1.5} gives the paper's eight. None: the library default (the paper's).
        `case`: the predictor's FeatureCase whose initial state is analysed (None: the model's own feature).
        """
        case = case or self.predictor.case(None)
        key = self._mechanisms_key(controls_raw, factors, case)
        cached = self._mechanisms.get(key)
        if cached is not None:
            return cached
        from nemsim.analysis.counterfactual import mechanism_response

        kwargs: dict[str, Any] = {} if key[1] is None else {"factors": key[1]}
        raw = np.asarray(controls_raw, dtype=np.float64)
        # no inference_mode: the library owns its autograd settings
        predictor = self.predictor
        result = jsonable(mechanism_response(predictor.loaded, raw, x0=case.x0, **kwargs))
        self._mechanisms.put(key, result)
        return result
