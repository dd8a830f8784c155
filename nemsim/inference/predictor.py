"""``Predictor``: a checkpoint's model behind physical controls -- rollouts, profile metrics and meshes.

Controls enter in physical units (a mapping name -> value, one mapping per transition, or a (T, 14) /
(14,) array in ``CONTROL_NAMES`` order) and are normalized exactly once, into a ``ControlSchedule`` that
carries both forms from then on; a caller holding normalized controls builds the schedule with
``ControlSchedule.from_normalized`` and nothing converts them back and forth. A rollout runs the
checkpoint's model through a runtime (``nemsim.inference.runtime``: PyTorch or OpenVINO) from the scene's
initial state, built by the simulator with the configuration of the checkpoint's training data when it
records one, and returns the trajectory with its profile metrics (``nemsim.geometry.profile``) and the
stability guard's findings. A quarter-domain model (``nemsim.symmetry``) starts from that state averaged over
the scene's symmetries (the simulator's initial state is symmetric up to the sub-voxel rounding of its
distance transform), so each of its trajectories is exactly symmetric (``symmetric_size``), and
``rollout(..., quadrant=True)`` keeps it on the quadrant: no full field is built, the metrics and the
stability guard read a quarter of the voxels, and ``nemsim.symmetry.unfold`` rebuilds any state on demand.
A cross-section (trench) model (``domain = "section"``) the same on its cross-section: its default feature
is the trench of the scene's opening and mask (``served_scene``), and it knows no holes.

Geometry (``nemsim.geometry.feature``): a rollout may be of another feature than the scene's own
(``rollout(..., feature=...)``). ``case(feature)`` gives its ``FeatureCase``: the feature as built on the
grid, the per-case scene (``Feature.apply``) and x0 built from it exactly as the default one (the
checkpoint's simulator configuration, the symmetric mean for a quarter-domain model); the metrics and meshes
read the per-case scene. A kind the checkpoint was not trained on is refused
(``range_check.UnknownGeometry``), one that does not fit the grid too (ValueError, ``Feature.check``); a
known kind outside its trained ranges is rolled out, and ``geometry_outside`` says why it is not trusted.
The last ``CASES_KEPT`` cases are kept (an x0 costs the simulator's initial-state build).
"""

from __future__ import annotations

import functools
import inspect
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, from_normalized, to_normalized
from nemsim.geometry.feature import Feature
from nemsim.inference import range_check
from nemsim.inference.checkpoint import (
    LoadedModel,
    TrainedGeometry,
    checkpoint_geometry,
    checkpoint_id,
    load_checkpoint,
)
from nemsim.inference.precision import machine, resolve_precision
from nemsim.inference.runtime import BACKENDS, Runtime, compile_model, openvino_available
from nemsim.symmetry import FieldFold, model_fold, section_line

log = logging.getLogger(__name__)

BACKEND_CHOICES: tuple[str, ...] = ("auto", *BACKENDS)  # "auto": openvino when installed, else torch
STATE_BOUND = 1.5  # |normalized SDF| above this is outside anything the model learned (data are in [-1, 1])
CASES_KEPT = 8  # feature cases (per-case scene and x0) a predictor keeps (module docstring)

Controls = Mapping[str, float] | Sequence[Mapping[str, float]] | np.ndarray


@dataclass(frozen=True, eq=False)
class ControlSchedule:
    """Controls per transition in both forms: ``raw`` (T, 14) float64 physical units and ``normalized``
    (T, 14) float32, what the model reads. Build it with ``control_schedule`` or ``from_normalized``."""

    raw: np.ndarray  # (T, 14) float64, physical units
    normalized: np.ndarray  # (T, 14) float32

    @classmethod
    def physical(cls, raw: np.ndarray) -> ControlSchedule:
        """From (T, 14) physical controls: the one place they are normalized."""
        raw = np.array(raw, dtype=np.float64, copy=True).reshape(-1, len(CONTROL_NAMES))  # (T, 14)
        return cls(raw, np.asarray(to_normalized(raw), dtype=np.float32))

    @classmethod
    def from_normalized(cls, u: Any, steps: int | None = None) -> ControlSchedule:
        """From normalized controls (T, 14), or (14,) repeated over ``steps`` transitions; the model reads
        them as given, the physical values are derived once (for reports and range checks)."""
        u = np.asarray(u, dtype=np.float32)
        u = _per_transition(u, steps)  # (T, 14)
        return cls(np.asarray(from_normalized(u.astype(np.float64)), dtype=np.float64), u.copy())

    @property
    def steps(self) -> int:
        return int(self.raw.shape[0])


def _per_transition(rows: np.ndarray, steps: int | None) -> np.ndarray:
    """(T, 14) from a (14,) vector repeated ``steps`` times or a (T, 14) array (``steps`` must be T)."""
    n = len(CONTROL_NAMES)
    if rows.ndim == 1 and rows.shape[0] == n:
        if steps is None or steps < 1:
            raise ValueError(f"constant controls need steps >= 1, got {steps}")
        return np.repeat(rows[None], steps, axis=0)
    if rows.ndim != 2 or rows.shape[1] != n or rows.shape[0] < 1:
        raise ValueError(f"controls must be ({n},) or (T, {n}), got shape {rows.shape}")
    if steps is not None and steps != rows.shape[0]:
        raise ValueError(f"{rows.shape[0]} control sets but steps = {steps}: give one per transition")
    return rows


def _row(controls: Mapping[str, float]) -> np.ndarray:
    """(14,) float64 from a mapping naming every control exactly once."""
    unknown = sorted(set(controls) - set(CONTROL_NAMES))
    missing = [n for n in CONTROL_NAMES if n not in controls]
    if unknown or missing:
        raise ValueError(
            f"controls must name each of {list(CONTROL_NAMES)}; unknown {unknown}, missing {missing}"
        )
    return np.array([float(controls[n]) for n in CONTROL_NAMES], dtype=np.float64)


def control_schedule(controls: Controls | ControlSchedule, steps: int | None = None) -> ControlSchedule:
    """A ``ControlSchedule`` from physical controls.

    Args:
        controls: a mapping name -> value (constant; needs ``steps``), a sequence of mappings (one per
            transition), a (14,) or (T, 14) array in ``CONTROL_NAMES`` order, or a ``ControlSchedule``
            (returned as it is).
        steps: transitions; for time-varying controls it must equal their number (or be None).
    """
    if isinstance(controls, ControlSchedule):
        if steps is not None and steps != controls.steps:
            raise ValueError(f"the schedule has {controls.steps} transitions but steps = {steps}")
        return controls
    if isinstance(controls, Mapping):
        rows = _row(controls)
    elif isinstance(controls, np.ndarray):
        rows = np.asarray(controls, dtype=np.float64)
    else:
        rows = np.stack([_row(c) for c in controls]) if len(controls) else np.zeros((0, len(CONTROL_NAMES)))
    return ControlSchedule.physical(_per_transition(rows, steps))


def stability_warnings(traj: np.ndarray, bound: float = STATE_BOUND) -> list[str]:
    """Readable warnings for a predicted trajectory (T+1, 2, D, H, W): the first step whose state is not
    finite, and the first step whose |value| exceeds ``bound`` (`nemsim stress` measures the same)."""
    return stability_report(traj, bound)[0]


def stability_report(traj: np.ndarray, bound: float = STATE_BOUND) -> tuple[list[str], int | None]:
    """(``stability_warnings``, the first step whose state is not finite or None).

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
    first_non_finite = None
    if not finite.all():
        k = first_non_finite = int(np.argmin(finite))
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
    return out, first_non_finite


@dataclass(frozen=True, eq=False)
class Prediction:
    """One rollout: the states, their profile metrics and what the stability guard found."""

    schedule: ControlSchedule
    # (T+1, 2, D, H, W) float32 normalized SDF (a view of ``out`` when one was given), or the folded part
    # (T+1, 2, D, h, w) of fields of lateral size ``full_size`` (``Predictor.rollout(..., quadrant=True)``;
    # ``fold`` says which: the quadrant, or a trench's cross-section)
    states: np.ndarray
    metrics: dict[str, np.ndarray]  # name -> (T+1,) values in nm (NaN where undefined)
    times_s: list[float]  # (T+1,)
    rollout_s: float
    metrics_s: float
    warnings: tuple[str, ...] = ()
    non_finite_from: int | None = None  # the first step whose state is not finite (NaN/Inf), None: none
    fold: FieldFold | None = None  # set when ``states`` holds a folded part (``nemsim.symmetry.FieldFold``)

    @property
    def steps(self) -> int:
        return self.schedule.steps

    @property
    def full_size(self) -> int | None:
        """The lateral size of the fields ``states`` is the folded part of (None: full fields)."""
        return None if self.fold is None else self.fold.n


def served_scene(loaded: LoadedModel) -> Any:
    """The scene a checkpoint answers by default: its own, or for a cross-section (trench) model the trench of
    the scene's opening and mask (a section model knows no holes)."""
    f = model_fold(loaded.model)
    if f is not None and f.kind == "section":
        return replace(Feature.of(loaded.scene), kind="trench").apply(loaded.scene)
    return loaded.scene


@dataclass(frozen=True, eq=False)
class FeatureCase:
    """One feature on the checkpoint's grid: ``feature`` as built (mask in whole voxels), the per-case
    ``scene`` and its initial state ``x0`` (2, D, H, W) float32; ``default``: the scene's own feature."""

    feature: Feature
    scene: Any  # nemsim.scenes.Scene
    x0: np.ndarray
    default: bool


def _recorded_sim_config(raw: dict[str, Any]) -> tuple[Any, str]:
    """(SimConfig or None, how the initial state is built) from a checkpoint's ``sim_config`` record, read
    defensively: older checkpoints have none, and an unreadable one falls back to the simulator defaults."""
    from nemsim.sim.config import SimConfig

    recorded = raw.get("sim_config")
    if not isinstance(recorded, dict) or not recorded:
        return None, "simulator defaults (the checkpoint records no simulator configuration)"
    try:
        return SimConfig.from_record(recorded), "the checkpoint's simulator configuration (sim_config)"
    except (TypeError, ValueError) as exc:
        log.warning("checkpoint sim_config unreadable (%s): initial state from the simulator defaults", exc)
        return None, "simulator defaults (the checkpoint's simulator configuration could not be read)"


def resolve_backend(backend: str) -> str:
    """``"auto"`` -> ``"openvino"`` when it is installed, else ``"torch"``; other names are checked."""
    if backend not in BACKEND_CHOICES:
        raise ValueError(f"unknown backend {backend!r}; expected one of {list(BACKEND_CHOICES)}")
    if backend == "auto":
        return "openvino" if openvino_available() else "torch"
    return backend


class Predictor:
    """A loaded checkpoint behind physical controls (module docstring). Thread-safe; no caching."""

    def __init__(
        self,
        loaded: LoadedModel,
        *,
        model_id: str | None = None,
        backend: str = "auto",
        precision: str = "f32",
        threads: int = 1,
        x0: np.ndarray | None = None,
    ) -> None:
        """Args:
            loaded: from ``load_checkpoint``.
            model_id: how responses name the model (default: the checkpoint's stem).
            backend: "auto", "torch" or "openvino" (which falls back to torch, logged, when unavailable).
            precision: "f32", "bf16" or "auto" (bf16 where the device computes in it, else f32:
                ``nemsim.inference.precision``). threads: OpenVINO threads per rollout.
            x0: (2, D, H, W) initial state; default the scene's, built as the checkpoint's data were.
        """
        self.loaded = loaded
        self.scene = loaded.scene
        self.model_id = model_id or (loaded.path.stem if loaded.path else loaded.name)
        backend = resolve_backend(backend)
        self.precision_requested = precision
        chosen = resolve_precision(precision, "cuda" if backend == "cuda" else "cpu")
        self.runtime: Runtime = compile_model(loaded.model, backend, chosen, threads)  # type: ignore[arg-type]
        self.sim_config, source = _recorded_sim_config(loaded.raw or {})
        self._fold = model_fold(loaded.model)
        self.scene = served_scene(loaded)
        if x0 is None:
            x0 = self._initial_state(self.scene)
            if self._fold is not None:
                source += ", averaged over the scene's symmetries"
        else:
            source = "given by the caller"
        self.x0 = np.asarray(x0, dtype=np.float32)  # (2, D, H, W)
        # a quarter-domain model from a symmetric x0: every state of its rollouts is exactly symmetric
        x0_t = torch.as_tensor(self.x0)
        symmetric = self._fold is not None and bool(torch.equal(x0_t, self._fold.symmetrize(x0_t)))
        self.symmetric_fold: FieldFold | None = self._fold if symmetric else None
        self.initial_state_source = source
        expected = tuple(self.scene.state_shape)
        if self.x0.shape != expected:
            raise ValueError(
                f"initial state has shape {self.x0.shape}, scene {self.scene.name!r} needs {expected}"
            )
        self.geometry: TrainedGeometry = checkpoint_geometry(loaded)
        self.default_feature = Feature.of(self.scene)
        self._default_case = FeatureCase(self.default_feature, self.scene, self.x0, True)
        self._cases: OrderedDict[Feature, FeatureCase] = OrderedDict()
        self._cases_lock = threading.Lock()
        ranges = (loaded.raw or {}).get("control_ranges") or {}
        # the training box: what the checkpoint recorded at training time, else the current design range
        self.train_range = {
            s.name: (
                float(ranges.get(s.name, {}).get("low", s.low)),
                float(ranges.get(s.name, {}).get("high", s.high)),
            )
            for s in CONTROL_SPECS
        }

    @classmethod
    def from_checkpoint(
        cls, path: str | Path, *, scene: str | None = None, device: str = "cpu", **kwargs: Any
    ) -> Predictor:
        """Load ``path`` (``load_checkpoint``: weights-only, verified) and build its predictor; the model id
        is the file's stem and the first 12 hex digits of its SHA-256.

        Args:
            scene: the scene name the checkpoint must be trained on (CheckpointMismatch otherwise); None: any.
            kwargs: ``Predictor``'s (backend, precision, threads, x0).
        """
        path = Path(path)
        loaded = load_checkpoint(path, scene=scene, device=device)
        return cls(loaded, model_id=f"{path.stem}@{checkpoint_id(path)}", **kwargs)

    # --- facts ----------------------------------------------------------------------------------------
    @property
    def model(self) -> torch.nn.Module:
        return self.loaded.model

    @property
    def n_params(self) -> int:
        return int(sum(p.numel() for p in self.model.parameters() if p.requires_grad))

    def runtime_info(self) -> dict[str, Any]:
        """What rolls out and why: the runtime's ``describe()`` (backend, precision, threads, fallback
        reason; OpenVINO also the precision its plugin runs), ``precision_requested`` ("auto": the CPU's
        default) and the CPU with its bfloat16 flags (``nemsim.inference.precision.machine``)."""
        return {**self.runtime.describe(), "precision_requested": self.precision_requested, **machine()}

    @property
    def horizon_steps(self) -> int:
        """Transitions of the scene's trajectories (what the model was trained on)."""
        return int(self.scene.n_transitions)

    @property
    def control_saturation(self) -> tuple[float, float] | None:
        """The model's control saturation (knee, limit) in box half-widths, None if it reads controls as
        given (``nemsim.model.saturation``)."""
        sat = getattr(getattr(self.model, "config", None), "control_saturation", None)
        return None if sat is None else (float(sat[0]), float(sat[1]))

    @functools.cached_property
    def supports_mechanisms(self) -> bool:
        """Only NEMSim models expose event intensities and attributions (forward(..., return_aux=True))."""
        return "return_aux" in inspect.signature(self.model.forward).parameters

    # --- geometry -------------------------------------------------------------------------------------
    def _initial_state(self, scene: Any) -> np.ndarray:
        """x0 (2, D, H, W) of a (per-case) scene, built as the checkpoint's data were; a quarter- or
        section-domain model's the symmetric mean (module docstring)."""
        from nemsim.sim import initial_state

        config = self.sim_config
        if config is not None and scene.kind == "trench" and config.domain == "quarter":
            config = replace(config, domain="full")  # a trench has no quadrant; x0 is the same field
        if config is not None and scene.kind != "trench" and config.domain == "section":
            config = replace(config, domain="full")  # a hole has no cross-section
        x0 = initial_state(scene, config)
        if self._fold is not None:
            x0 = self._fold.symmetrize(torch.as_tensor(x0)).numpy()
        return np.asarray(x0, dtype=np.float32)

    def case(self, feature: Feature | None = None) -> FeatureCase:
        """The ``FeatureCase`` of ``feature`` (None: the scene's own).

        Raises:
            range_check.UnknownGeometry: a kind the checkpoint was not trained on (names the kinds it knows).
            ValueError: the feature does not fit the scene's grid (one line, ``Feature.check``).
        """
        if feature is None:
            return self._default_case
        range_check.check_kind(feature, self.geometry)
        feature.check(self.scene)
        built = feature.on_grid(self.scene)
        if built == self.default_feature:
            return self._default_case
        with self._cases_lock:
            found = self._cases.get(built)
            if found is not None:
                self._cases.move_to_end(built)
                return found
        scene = built.apply(self.scene)
        made = FeatureCase(built, scene, self._initial_state(scene), False)
        with self._cases_lock:
            self._cases[built] = made
            while len(self._cases) > CASES_KEPT:
                self._cases.popitem(last=False)
        return made

    def simulator_config(self, scene: Any) -> Any:
        """The simulator configuration for a (per-case) scene: the checkpoint's (None: the defaults), a
        trench on its cross-section (``SimConfig.domain`` = "section": its mean evolution is 2-D)."""
        if scene.kind != "trench":
            return self.sim_config
        from nemsim.sim.config import SimConfig

        return replace(self.sim_config or SimConfig(), domain="section")

    def geometry_outside(self, feature: Feature) -> str | None:
        """Why ``feature`` (as built, ``case(feature).feature``) is outside the trained geometry, or None."""
        return range_check.geometry_outside(feature, self.geometry)

    # --- controls -------------------------------------------------------------------------------------
    def schedule(self, controls: Controls | ControlSchedule, steps: int | None = None) -> ControlSchedule:
        """``control_schedule(controls, steps)``."""
        return control_schedule(controls, steps)

    def check_range(
        self, schedule: ControlSchedule, policy: str = "allow"
    ) -> tuple[ControlSchedule, list[str], list[range_check.Excursion], bool]:
        """(schedule to use, warnings, excursions of the given controls, clipped?) for controls outside the
        training box under ``policy`` (``range_check``); ``range_check.Refused`` under "refuse"."""
        raw, warnings, found, clipped = range_check.apply(
            schedule.raw, self.train_range, policy, self.control_saturation
        )
        return (ControlSchedule.physical(raw) if clipped else schedule), warnings, found, clipped

    # --- rollouts -------------------------------------------------------------------------------------
    def rollout(
        self,
        controls: Controls | ControlSchedule,
        steps: int | None = None,
        *,
        out: torch.Tensor | None = None,
        quadrant: bool = False,
        feature: Feature | None = None,
    ) -> Prediction:
        """Roll the model out from the initial state under ``controls`` (physical units, see
        ``control_schedule``) and compute the profile metrics of every state.

        Args:
            out: optional float32 buffer (>= T+1, *``state_shape(quadrant)``) the states are written into
                (the returned ``states`` is then a view of it, valid while the caller does not reuse it).
            quadrant: return the states' folded part (quadrant or cross-section; ``Prediction.fold``
                set), when the rollouts are exactly symmetric (``symmetric_size``); otherwise
                the full fields, as without it.
            feature: the feature etched (None: the scene's own); ``case`` says what is refused.
        """
        from nemsim.evaluation.rollout import rollout

        case = self.case(feature)
        sched = self.schedule(controls, steps)
        T = sched.steps
        fold_ = self.symmetric_fold if quadrant else None
        x0 = torch.from_numpy(case.x0)[None]  # (1, 2, D, H, W)
        if fold_ is not None:
            x0 = fold_.fold(x0).contiguous()  # the model's own domain: the rollout stays there
        u = torch.from_numpy(sched.normalized)[None]  # (1, T, 14)
        t0 = time.perf_counter()
        whole = getattr(self.runtime, "rollout", None)  # CUDA graphs: a constant-control rollout, one replay
        with torch.inference_mode():
            if whole is not None and T > 0 and bool((sched.normalized == sched.normalized[0]).all()):
                traj = whole(x0, u[:, 0], T, copy=False)[0]  # (T+1, 2, D, H, W) on the GPU
                traj = traj.cpu() if out is None else out[: T + 1].copy_(traj)
            else:
                traj = rollout(self.runtime, x0, u, T, out=None if out is None else out[None])[0]  # type: ignore[arg-type]
        t1 = time.perf_counter()
        states = traj.numpy()  # (T+1, 2, D, H, W)
        metrics = self.metrics(states, case.scene)
        t2 = time.perf_counter()
        dt = float(self.scene.snapshot_dt_s)
        warnings, non_finite_from = stability_report(states)
        return Prediction(
            schedule=sched,
            states=states,
            metrics=metrics,
            times_s=[round(k * dt, 6) for k in range(T + 1)],
            rollout_s=t1 - t0,
            metrics_s=t2 - t1,
            warnings=tuple(warnings),
            non_finite_from=non_finite_from,
            fold=fold_,
        )

    @property
    def symmetric_size(self) -> int | None:
        """The lateral size of the fields every rollout is exactly symmetric in (None: not symmetric)."""
        return None if self.symmetric_fold is None else self.symmetric_fold.n

    def state_shape(self, quadrant: bool = False) -> tuple[int, ...]:
        """(2, D, H, W) of a rollout's states, or (2, D, c, c) for ``rollout(..., quadrant=True)`` when the
        rollouts are exactly symmetric."""
        if quadrant and self.symmetric_fold is not None:
            return (*self.x0.shape[:2], *self.symmetric_fold.plane)
        return tuple(self.x0.shape)

    def metrics(self, states: np.ndarray, scene: Any = None) -> dict[str, np.ndarray]:
        """Profile metrics (nm) of states (T+1, 2, D, H, W), or of their quadrant or cross-section
        (``rollout(..., quadrant=True)``): name -> (T+1,), NaN where undefined (``measured_profile_metrics``);
        ``scene``: the per-case scene (None: the checkpoint's)."""
        from nemsim.geometry.profile import measured_profile_metrics

        f = self.symmetric_fold
        if f is not None and f.kind == "section" and tuple(states.shape[-2:]) == f.plane:
            # a trench's line profile (T+1, 2, D, 1, n), the cross-section's row across x
            states = section_line(torch.from_numpy(states), f.n).numpy()
        return measured_profile_metrics(states, self.scene if scene is None else scene)

    def warm_up(self, steps: int) -> None:
        """One short rollout so the first request does not pay for allocation / graph compilation; on CUDA
        graphs also the scene's whole constant-control rollout (its graph captured, its fused call compiled
        for the layout the whole rollout feeds it)."""
        if steps <= 0:
            return
        from nemsim.evaluation.rollout import rollout

        u = torch.zeros(1, steps, len(CONTROL_NAMES))
        x0 = torch.from_numpy(self.x0)[None]  # (1, 2, D, H, W)
        whole = getattr(self.runtime, "rollout", None)
        with torch.inference_mode():
            rollout(self.runtime, x0, u, steps, keep=False)  # type: ignore[arg-type]
            if whole is not None:
                whole(x0, u[:, 0], int(self.scene.n_transitions), copy=False)

    # --- meshes ---------------------------------------------------------------------------------------
    def mesh(self, field: np.ndarray, fmt: str, metadata: dict[str, Any] | None = None,
             scene: Any = None) -> bytes:
        """File bytes (glb, ply, obj, stl or vtp) of the zero-level surface of one channel's field (D, H,
        W), in nm, with ``metadata`` as provenance (``nemsim.geometry.mesh``); ``scene``: the per-case
        scene whose frame the mesh is placed in (None: the checkpoint's)."""
        from nemsim.geometry.mesh import export_mesh, surface_mesh

        scene = self.scene if scene is None else scene
        return export_mesh(surface_mesh(np.asarray(field, dtype=np.float32), scene, metadata), fmt)
