"""The service-side wrapper around a loaded checkpoint: rollouts, profile metrics, meshes, counterfactuals.

No physics here: the rollout is `nemsim.evaluation.rollout.rollout`, metrics are
`nemsim.geometry.profile.profile_metrics_batch` (profile_metrics over all steps), meshes
`nemsim.geometry.mesh`, mechanisms `nemsim.analysis.counterfactual.mechanism_response`. This module
adds what a server needs:

* a model id (checkpoint stem + the first 12 hex digits of the file's SHA-256);
* an LRU cache of finished rollouts keyed by (model id, normalized controls per transition, steps); the
  key's hash is the rollout id, so a repeat, a follow-up mesh request or a request giving the same
  controls normalized recomputes nothing. States are kept as float16 (what the API returns anyway) and the
  cache is bounded in entries and bytes, and segmented (`_LRU`) so one-off rollouts do not evict the ones
  in use;
* cache look-ups apart from computations (`lookup_rollout` / `compute_rollout`, `cached_mesh` / `mesh`,
  `cached_mechanisms` / `mechanisms`), so the app answers cache hits on the event loop and admits the
  computations through its own gates (`service.scheduler`). This class does no admission control.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import logging
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, to_normalized

log = logging.getLogger(__name__)


class ServiceBusy(RuntimeError):
    """Too many requests are computing or waiting; retry later."""


class UnknownRollout(KeyError):
    """No cached rollout has this id (never computed here, or evicted)."""


@dataclass(frozen=True)
class RolloutResult:
    id: str
    model_id: str
    steps: int
    controls_raw: np.ndarray  # (T, 14) physical units
    states: np.ndarray  # (T+1, 2, D, H, W) float16, normalized SDF
    metrics: dict[str, list[float | None]]  # name -> (T+1,) values in nm, None where not finite
    times_s: list[float]  # (T+1,)
    rollout_ms: float
    metrics_ms: float
    warnings: tuple[str, ...] = ()  # stability guard findings (non-finite or out-of-range states)


STATE_BOUND = 1.5  # |normalized SDF| above this is outside anything the model learned (data are in [-1, 1])


def stability_warnings(traj: np.ndarray, bound: float = STATE_BOUND) -> list[str]:
    """Readable warnings for a predicted trajectory (T+1, 2, D, H, W): the first step whose state is not
    finite, and the first step whose |value| exceeds ``bound`` (`nemsim stress` measures the same).

    Two reductions per step and no temporary of the trajectory's size: a step is finite exactly when its
    max and min are (both propagate NaN and carry an infinity); only non-finite steps are scanned again
    to find their largest finite |value|."""
    flat = traj.reshape(traj.shape[0], -1)
    hi, lo = flat.max(axis=1), flat.min(axis=1)  # (T+1,) each
    finite = np.isfinite(hi) & np.isfinite(lo)
    peak = np.maximum(hi, -lo)
    for row in np.flatnonzero(~finite):
        ok = flat[row][np.isfinite(flat[row])]
        peak[row] = np.abs(ok).max() if ok.size else 0.0
    out: list[str] = []
    if not finite.all():
        k = int(np.argmin(finite))
        out.append(
            f"the prediction is not finite from step {k} on (NaN/Inf): states and metrics from there on "
            "are unusable"
        )
    if (peak > bound).any():
        k = int(np.argmax(peak > bound))
        out.append(
            f"the predicted field leaves the signed-distance range from step {k} on (|value| up to "
            f"{float(peak.max()):.3g}, data lie in [-1, 1]): the surrogate is unstable for these controls; "
            "treat later steps as unreliable"
        )
    return out


class _LRU:
    """Least-recently-used cache bounded in entries and, with `weigh`, in bytes (an entry larger than
    the whole budget is not kept). Segmented, so a stream of one-off entries cannot flush the entries in
    use: a new entry starts on probation; a hit moves it to the protected segment (at most
    `PROTECTED_SHARE` of both bounds; its least recent entries step back to probation); eviction takes
    the least recent probation entry first. Under a flood of distinct uncached rollouts the rollouts
    that clients come back to (repeats, their meshes) stay cached."""

    PROTECTED_SHARE = 0.5

    def __init__(
        self, size: int, max_bytes: int | None = None, weigh: Callable[[Any], int] | None = None
    ) -> None:
        self.size = size
        self.max_bytes = max_bytes
        self.weigh = weigh or (lambda value: 0)
        self.bytes = 0  # both segments
        self._probation: OrderedDict[Any, Any] = OrderedDict()
        self._protected: OrderedDict[Any, Any] = OrderedDict()
        self._protected_bytes = 0
        self._lock = threading.Lock()

    def get(self, key: Any) -> Any | None:
        with self._lock:
            if key in self._protected:
                self._protected.move_to_end(key)
                return self._protected[key]
            if key not in self._probation:
                return None
            value = self._probation.pop(key)
            self._protected[key] = value
            self._protected_bytes += self.weigh(value)
            while len(self._protected) > 1 and self._protected_over():
                old_key, old = self._protected.popitem(last=False)
                self._protected_bytes -= self.weigh(old)
                self._probation[old_key] = old  # most recent end of probation
            return value

    def put(self, key: Any, value: Any) -> None:
        weight = self.weigh(value)
        if self.size <= 0 or (self.max_bytes is not None and weight > self.max_bytes):
            return
        with self._lock:
            if key in self._protected:
                old = self._protected[key]
                self._protected[key] = value
                self._protected_bytes += weight - self.weigh(old)
                self.bytes += weight - self.weigh(old)
            else:
                if key in self._probation:
                    self.bytes -= self.weigh(self._probation.pop(key))
                self._probation[key] = value
                self.bytes += weight
            while len(self) > self.size or self._over_budget():
                segment = self._probation if self._probation else self._protected
                _, old = segment.popitem(last=False)
                self.bytes -= self.weigh(old)
                if segment is self._protected:
                    self._protected_bytes -= self.weigh(old)

    def _protected_over(self) -> bool:
        share = self.PROTECTED_SHARE
        over_bytes = self.max_bytes is not None and self._protected_bytes > share * self.max_bytes
        return len(self._protected) > share * self.size or over_bytes

    def _over_budget(self) -> bool:
        return self.max_bytes is not None and self.bytes > self.max_bytes

    def __len__(self) -> int:
        return len(self._probation) + len(self._protected)


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def checkpoint_sim_config(raw: dict[str, Any]) -> tuple[Any, str]:
    """(SimConfig or None, how the initial state is built) from a checkpoint's `sim_config`: the
    simulator configuration of its training data (the data file's `generator` attribute, whose
    `config` entry is `SimConfig.to_meta`; a bare `to_meta` dict is accepted too). Read defensively:
    older checkpoints have none, and an unreadable one falls back to the simulator's defaults."""
    from nemsim.sim.config import SimConfig

    recorded = raw.get("sim_config")
    if not isinstance(recorded, dict) or not recorded:
        return None, "simulator defaults (the checkpoint records no simulator configuration)"
    try:
        return SimConfig.from_record(recorded), "the checkpoint's simulator configuration (sim_config)"
    except (TypeError, ValueError) as exc:
        log.warning("checkpoint sim_config unreadable (%s): initial state from the simulator defaults", exc)
        return None, "simulator defaults (the checkpoint's simulator configuration could not be read)"


def initial_state(loaded: Any) -> np.ndarray:
    """(2, D, H, W) float32 normalized SDF of the scene's initial geometry, built by the simulator with
    the configuration of the checkpoint's data when it records one (`checkpoint_sim_config`)."""
    from nemsim.sim import initial_state as build  # the simulator's SDF of the scene's initial geometry

    config, _ = checkpoint_sim_config(loaded.raw or {})
    return np.asarray(build(loaded.scene, config), dtype=np.float32)


class Surrogate:
    """A loaded checkpoint plus cache and admission control. Thread-safe."""

    def __init__(
        self,
        loaded: Any,
        *,
        model_id: str,
        x0: np.ndarray | None = None,
        cache_size: int = 32,
        cache_bytes: int | None = None,
        runtime_backend: str = "openvino",
        runtime_precision: str = "bf16",
        runtime_threads: int = 1,
    ) -> None:
        from nemsim.inference.runtime import compile_model

        self.loaded = loaded
        # rollouts run through the fast CPU runtime (PyTorch eager when openvino is missing, logged)
        self.predictor = compile_model(loaded.model, runtime_backend, runtime_precision, runtime_threads)  # type: ignore[arg-type]
        self.model_id = model_id
        self.scene = loaded.scene
        self.x0 = initial_state(loaded) if x0 is None else np.asarray(x0, dtype=np.float32)
        self.initial_state_source = (
            checkpoint_sim_config(loaded.raw or {})[1] if x0 is None else "given by the caller"
        )
        expected = tuple(self.scene.state_shape)
        if self.x0.shape != expected:
            raise ValueError(
                f"initial state has shape {self.x0.shape}, scene {self.scene.name!r} needs {expected}"
            )
        # cache_bytes: the budget of the rollout cache (states dominate: ~17 MB per 100-step `small`
        # rollout); meshes get a quarter of it on top
        self._rollouts = _LRU(cache_size, cache_bytes, lambda r: int(r.states.nbytes))
        self._meshes = _LRU(4 * cache_size, None if cache_bytes is None else cache_bytes // 4, len)
        self._mechanisms = _LRU(cache_size)
        self._buffers: list[torch.Tensor] = []  # idle trajectory buffers (`_take_buffer`)
        self._buffers_lock = threading.Lock()
        ranges = (loaded.raw or {}).get("control_ranges") or {}
        specs = {s.name: s for s in CONTROL_SPECS}
        # train range: what the checkpoint recorded at training time, else the current design range
        self.train_range = {
            n: (
                float(ranges.get(n, {}).get("low", specs[n].low)),
                float(ranges.get(n, {}).get("high", specs[n].high)),
            )
            for n in CONTROL_NAMES
        }

    # --- construction ---------------------------------------------------------------------------
    @classmethod
    def from_checkpoint(cls, path: str | Path, **kwargs: Any) -> Surrogate:
        from service.loading import load_checkpoint_safely  # weights-only: no code from the file runs

        path = Path(path)
        loaded = load_checkpoint_safely(path)
        model_id = f"{path.stem}@{file_sha256(path)[:12]}"
        return cls(loaded, model_id=model_id, **kwargs)

    # --- facts --------------------------------------------------------------------------------------
    @property
    def n_params(self) -> int:
        return int(sum(p.numel() for p in self.loaded.model.parameters() if p.requires_grad))

    @property
    def horizon_steps(self) -> int:
        return int(self.scene.n_transitions)

    @property
    def control_saturation(self) -> tuple[float, float] | None:
        """The model's control saturation (knee, limit) in box half-widths, None if it reads controls as
        given (``nemsim.model.saturation``)."""
        sat = getattr(getattr(self.loaded.model, "config", None), "control_saturation", None)
        return None if sat is None else (float(sat[0]), float(sat[1]))

    def warnings_for(self, controls_raw: np.ndarray) -> list[str]:
        """Readable warnings for controls outside the training range. controls_raw: (T, 14) or (14,)."""
        from service.extrapolation import excursions

        return [e.describe() for e in excursions(controls_raw, self.train_range, self.control_saturation)]

    @staticmethod
    def rollout_id(model_id: str, u_norm: np.ndarray, steps: int) -> str:
        h = hashlib.sha256(model_id.encode())
        h.update(str(steps).encode())
        h.update(np.ascontiguousarray(u_norm, dtype="<f4").tobytes())
        return h.hexdigest()[:24]

    # --- rollouts ---------------------------------------------------------------------------------
    def get_rollout(self, rollout_id: str) -> RolloutResult:
        result = self._rollouts.get(rollout_id)
        if result is None:
            raise UnknownRollout(rollout_id)
        return result

    def lookup_rollout(self, controls_raw: np.ndarray) -> tuple[str, RolloutResult | None]:
        """(rollout id, the cached result or None) of (T, 14) physical controls, one row per transition."""
        controls_raw = np.asarray(controls_raw, dtype=np.float64)
        u_norm = np.asarray(to_normalized(controls_raw), dtype=np.float32)  # (T, 14)
        rid = self.rollout_id(self.model_id, u_norm, int(controls_raw.shape[0]))
        return rid, self._rollouts.get(rid)

    def compute_rollout(self, controls_raw: np.ndarray) -> tuple[RolloutResult, bool]:
        """Roll out and cache (T, 14) physical controls (blocking). Returns (result, served_from_cache):
        an identical request may have finished while this one waited for a slot."""
        controls_raw = np.asarray(controls_raw, dtype=np.float64)
        u_norm = np.asarray(to_normalized(controls_raw), dtype=np.float32)  # (T, 14)
        rid = self.rollout_id(self.model_id, u_norm, int(controls_raw.shape[0]))
        cached = self._rollouts.get(rid)
        if cached is not None:
            return cached, True
        result = self._compute(rid, controls_raw, u_norm)
        self._rollouts.put(rid, result)
        return result, False

    def rollout(self, controls_raw: np.ndarray) -> tuple[RolloutResult, bool]:
        """Cached or computed rollout of (T, 14) physical controls (blocking; no admission control)."""
        _, cached = self.lookup_rollout(controls_raw)
        return (cached, True) if cached is not None else self.compute_rollout(controls_raw)

    def _compute(self, rid: str, controls_raw: np.ndarray, u_norm: np.ndarray) -> RolloutResult:
        from nemsim.evaluation.rollout import rollout
        from nemsim.geometry.profile import profile_metrics_batch

        steps = u_norm.shape[0]
        x0 = torch.from_numpy(self.x0)[None]  # (1, 2, D, H, W)
        u = torch.from_numpy(u_norm)[None]  # (1, T, 14)
        buf = self._take_buffer(steps)  # (>= T+1, 2, D, H, W) float32
        try:
            t0 = time.perf_counter()
            traj_t = buf[: steps + 1]  # (T+1, 2, D, H, W)
            with torch.inference_mode():  # the states are written straight into the buffer
                rollout(self.predictor, x0, u, steps, out=buf[None])  # type: ignore[arg-type]
            t1 = time.perf_counter()
            traj = traj_t.numpy()
            metrics = {
                k: [v if math.isfinite(v) else None for v in vals.tolist()]  # JSON has no NaN / Inf
                for k, vals in profile_metrics_batch(traj, self.scene).items()
            }
            t2 = time.perf_counter()
            guard = stability_warnings(traj)
            states = traj_t.half().numpy()  # (T+1, 2, D, H, W) float16 (torch's conversion is vectorized)
        finally:
            self._give_back(buf)
        if guard:
            log.warning("rollout %s: %s", rid, "; ".join(guard))
        dt = float(self.scene.snapshot_dt_s)
        return RolloutResult(
            id=rid,
            model_id=self.model_id,
            steps=steps,
            controls_raw=controls_raw,
            states=states,
            metrics=metrics,
            times_s=[round(k * dt, 6) for k in range(steps + 1)],
            rollout_ms=1e3 * (t1 - t0),
            metrics_ms=1e3 * (t2 - t1),
            warnings=tuple(guard),
        )

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
            return torch.empty((steps + 1, *self.x0.shape), dtype=torch.float32)

    def _give_back(self, buf: torch.Tensor) -> None:
        with self._buffers_lock:
            self._buffers.append(buf)

    def warm_up(self, steps: int) -> None:
        """One short uncached rollout so the first request does not pay for allocation/JIT."""
        if steps <= 0:
            return
        from nemsim.evaluation.rollout import rollout

        u = torch.zeros(1, steps, len(CONTROL_NAMES))
        with torch.inference_mode():
            rollout(self.predictor, torch.from_numpy(self.x0)[None], u, steps, keep=False)  # type: ignore[arg-type]

    # --- meshes -------------------------------------------------------------------------------------
    def warm_up_meshes(self, formats: tuple[str, ...] = ("glb", "ply", "obj", "stl")) -> None:
        """Extract and export the initial Si surface once per format, so the first mesh request does not
        pay for imports and first-call compilation (about 1.5 s on `small`)."""
        from nemsim.geometry.mesh import export_mesh, surface_mesh

        mesh = surface_mesh(self.x0[1], self.scene, {"warm_up": True})
        for fmt in formats:
            export_mesh(mesh, fmt)

    def cached_mesh(self, result: RolloutResult, step: int, channel: str, fmt: str) -> bytes | None:
        return self._meshes.get((result.id, step, channel, fmt))

    def mesh(self, result: RolloutResult, step: int, channel: str, fmt: str) -> bytes:
        """File bytes of the zero-level surface of one channel at one step (cached; blocking)."""
        key = (result.id, step, channel, fmt)
        data = self._meshes.get(key)
        if data is not None:
            return data
        from nemsim.geometry.mesh import export_mesh, surface_mesh

        ch = 0 if channel == "mask" else 1
        field_ = result.states[step, ch].astype(np.float32)  # (D, H, W)
        metadata = {
            "model_id": self.model_id,
            "rollout_id": result.id,
            "step": step,
            "time_s": result.times_s[step],
            "channel": channel,
            "scene": self.scene.name,
            "controls": {
                n: float(v)
                for n, v in zip(CONTROL_NAMES, result.controls_raw[max(step - 1, 0)], strict=True)
            },
        }
        data = export_mesh(surface_mesh(field_, self.scene, metadata), fmt)
        self._meshes.put(key, data)
        return data

    # --- mechanisms ---------------------------------------------------------------------------------
    @functools.cached_property
    def supports_mechanisms(self) -> bool:
        """Only NEMSim models expose event intensities and attributions (forward(..., return_aux=True))."""
        return "return_aux" in inspect.signature(self.loaded.model.forward).parameters

    @staticmethod
    def _mechanisms_key(controls_raw: np.ndarray, factors: list[float] | None) -> tuple[bytes, Any]:
        if not factors:
            return np.asarray(controls_raw, dtype="<f8").tobytes(), None
        levels = sorted({1.0, *map(float, factors)})
        pairs = tuple((a, b) for a in levels for b in levels if (a, b) != (1.0, 1.0))
        return np.asarray(controls_raw, dtype="<f8").tobytes(), pairs

    def cached_mechanisms(
        self, controls_raw: np.ndarray, factors: list[float] | None
    ) -> dict[str, Any] | None:
        return self._mechanisms.get(self._mechanisms_key(controls_raw, factors))

    def mechanisms(self, controls_raw: np.ndarray, factors: list[float] | None) -> dict[str, Any]:
        """`mechanism_response` for one base control vector (cached), JSON-ready (`schemas.jsonable`:
        plain lists and floats, non-finite as None), so a cache hit costs no conversion.

        `factors` are flux multiplier levels; the interventions are every (s_Cl+, s_Cl) pair of the levels
        and 1, except (1, 1) -- {0.5, 1.5} gives the paper's eight. None: the library default (the paper's).
        """
        from nemsim.analysis.counterfactual import mechanism_response
        from service.schemas import jsonable

        key = self._mechanisms_key(controls_raw, factors)
        cached = self._mechanisms.get(key)
        if cached is not None:
            return cached
        kwargs: dict[str, Any] = {} if key[1] is None else {"factors": key[1]}
        # no inference_mode: the library owns its autograd settings
        raw = np.asarray(controls_raw, dtype=np.float64)
        result = jsonable(mechanism_response(self.loaded, raw, x0=self.x0, **kwargs))
        self._mechanisms.put(key, result)
        return result
