"""The inverse-design spec: targets, held and bounded controls, the objective and its JSON form.

A spec asks for recipes (constant controls) whose profile metrics at one state index meet target values
within tolerances. The objective a search minimizes is

    J(u) = sum over targets of ((m(u) - value) / tol)^2  +  w * (+-) m_s(u) / 10 nm,

the second term for an optional secondary goal (``secondary_weight`` w; sign + to minimize metric m_s,
- to maximize). A target is met when |m - value| <= tol.

A search ranks and steers its recipes by J(u) + e * E(u) (``search_score``), E(u) = sum over controls of
(max(|u_j| - a, 0) / (1 - a))^2 in normalized controls, a = ``edge_start``: 0 inside the inner box, 1 per
control on a face of the training box, e = ``edge_weight``. Many recipes meet four targets with 14
controls, and the surrogate's error grows toward the faces and corners of the box
(benchmarks/small/extrapolation), so among equally good recipes the search prefers the inner ones; a
target that needs a face still gets it, at a small cost in J. Met and the reported objective stay J alone.
With e = 0.25 the simulator met the search's top recipe in its first run for 17 of 22 held-out targets,
against 14 with e = 0, and the simulator-corrected design met 19 of 22 on two sets of targets
(benchmarks/small/design_cost).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

import numpy as np

from nemsim.controls import check_control, control_index
from nemsim.geometry.soft_profile import SOFT_METRICS
from nemsim.scenes import Scene

TARGET_METRICS = SOFT_METRICS  # etch_depth, top_width, bottom_width, bowing, mask_loss
DEFAULT_TOL = {"etch_depth": 5.0, "top_width": 3.0, "bottom_width": 3.0, "mask_loss": 2.0, "bowing": 2.0}
SECONDARY_SCALE_NM = 10.0
MIN_TOL_NM = 0.1  # the finest tolerance accepted: far below a voxel (2 to 8 nm), far above rounding
Method = Literal["auto", "adam", "cma"]
Progress = Callable[[float, str], None]


class SearchCancelled(Exception):
    """The caller asked the search to stop."""


@dataclass(frozen=True)
class Target:
    value: float  # nm
    tol: float  # nm, > 0


@dataclass(frozen=True)
class SearchConfig:
    method: Method = "auto"  # auto: cma when the package is installed (benchmarks/small/inverse), else adam
    screen: int = 32  # quasi-random recipes rolled out before the refinement
    starts: int = 4  # Adam starts (the best screened recipes)
    iterations: int = 14  # Adam steps
    lr: float = 0.15  # Adam learning rate, normalized units (the box is 2 wide)
    min_separation: float = 0.25  # normalized distance between starts / between reported recipes
    batch: int = 8  # rollouts per no-gradient batch
    cma_evals: int = 200  # CMA-ES forward rollouts (about the gradient stage's cost)
    cma_sigma: float = 0.3
    secondary_weight: float = 0.1
    edge_weight: float = 0.25  # e of the search score (module docstring; benchmarks/small/design_cost)
    edge_start: float = 0.8  # a: where the edge term starts, normalized units


@dataclass(frozen=True)
class InverseSpec:
    """What to design (see ``spec_from_dict`` for the JSON form)."""

    targets: dict[str, Target]
    step: int | None = None  # state index the targets refer to (None: the scene's horizon)
    fixed: dict[str, float] = field(default_factory=dict)  # raw values of held controls
    bounds: dict[str, tuple[float, float]] = field(default_factory=dict)  # raw [low, high] per control
    secondary: tuple[str, str] | None = None  # (metric, "min" | "max")
    k: int = 3  # recipes reported
    search: SearchConfig = field(default_factory=SearchConfig)


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def target_range(metric: str, scene: Scene) -> tuple[float, float, str]:
    """(low, high, what bounds it): the physical range of profile metric ``metric`` in ``scene``, nm.

    The etch depth lies between 0 and the Si thickness, the widths (the neck's too) and the bowing between 0
    and the domain width, the mask loss between 0 and the mask thickness.
    """
    if metric not in (*TARGET_METRICS, "neck_width"):
        raise ValueError(f"unknown metric {metric!r}; expected one of {list(TARGET_METRICS)}")
    vox = scene.voxel_nm
    if metric == "etch_depth":
        return 0.0, scene.si_top * vox, "the Si thickness"
    if metric == "mask_loss":
        return 0.0, (scene.resist_top - scene.si_top) * vox, "the mask thickness"
    return 0.0, min(scene.nx, scene.ny) * vox, "the domain width"


def check_target(metric: str, value: Any, scene: Scene | None = None, where: str | None = None) -> float:
    """``value`` (nm) as a float, or ValueError naming ``where`` (default ``targets.<metric>``), the value
    and the accepted range: a finite number >= 0 and, with ``scene``, within ``target_range``."""
    where = where or f"targets.{metric}"
    v = _number(value, where)
    if scene is None:
        if v < 0:
            raise ValueError(f"{where} = {v:g} nm is impossible: {metric} is >= 0 nm")
        return v
    lo, hi, what = target_range(metric, scene)
    if not lo <= v <= hi:
        raise ValueError(f"{where} = {v:g} nm is outside the physical range {lo:g}..{hi:g} nm of {metric} "
                         f"(0 to {what} of scene {scene.name!r})")
    return v


def check_tolerance(metric: str, tol: Any, scene: Scene | None = None, where: str | None = None) -> float:
    """``tol`` (nm) as a float, or ValueError naming ``where`` (default ``targets.<metric>.tol``), the value
    and the accepted range: a finite number >= MIN_TOL_NM and, with ``scene``, at most the metric's range."""
    where = where or f"targets.{metric}.tol"
    t = _number(tol, where)
    hi = math.inf
    if scene is not None:
        lo_m, hi_m, _ = target_range(metric, scene)
        hi = hi_m - lo_m
    if not MIN_TOL_NM <= t <= hi:
        upper = f", at most {hi:g} nm (the range of {metric} in scene {scene.name!r})" if scene else ""
        raise ValueError(f"{where} = {t:g} nm is outside the accepted tolerances: at least {MIN_TOL_NM:g} nm"
                         f"{upper}")
    return t


def check_targets(targets: dict[str, Target], scene: Scene) -> None:
    """ValueError naming the first target value or tolerance outside its range in ``scene``
    (``check_target``, ``check_tolerance``): what an entry point checks once the scene is known."""
    for name, t in targets.items():
        check_target(name, t.value, scene, where=f"targets.{name}.value")
        check_tolerance(name, t.tol, scene)


def _control(name: Any, where: str) -> int:
    if not isinstance(name, str):
        raise ValueError(f"{where}: control names are strings, got {name!r}")
    try:
        return control_index(name)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def check_fixed(fixed: Any) -> dict[str, float]:
    """Held controls {name: raw value}, each admissible (``nemsim.controls.check_control``: finite,
    physically possible, within the scale guard, whole exponents); ValueError naming ``fixed.<name>``."""
    if not isinstance(fixed, dict):
        raise ValueError(f"fixed must be an object {{control: value}}, got {fixed!r}")
    out: dict[str, float] = {}
    for name, v in fixed.items():
        _control(name, "fixed")
        out[name] = check_control(name, _number(v, f"fixed.{name}"), where="fixed.")
    return out


def check_bounds(bounds: Any) -> dict[str, tuple[float, float]]:
    """Search bounds {name: (low, high)} in physical units, both ends admissible values of the control
    (``check_control``, fractions allowed) and low < high; ValueError naming ``bounds.<name>``."""
    if not isinstance(bounds, dict):
        raise ValueError(f"bounds must be an object {{control: [low, high]}}, got {bounds!r}")
    out: dict[str, tuple[float, float]] = {}
    for name, b in bounds.items():
        _control(name, "bounds")
        if not isinstance(b, list | tuple) or len(b) != 2:
            raise ValueError(f"bounds.{name} must be [low, high] in physical units, got {b!r}")
        lo, hi = (
            check_control(name, _number(v, f"bounds.{name}[{i}]"), where=f"bounds.{name}[{i}]: ", whole=False)
            for i, v in enumerate(b)
        )
        if not lo < hi:
            raise ValueError(f"bounds.{name}: need low < high, got [{lo:g}, {hi:g}]")
        out[name] = (lo, hi)
    return out


MAX_SEARCH_COUNT = 100_000  # the most screened recipes, starts, steps, batch or CMA-ES evaluations


def _search_config(s: dict[str, Any]) -> SearchConfig:
    """``SearchConfig`` from its JSON form (known keys only); ValueError naming ``search.<field>``."""
    for k, v in s.items():
        if k == "method":
            if v not in ("auto", "adam", "cma"):
                raise ValueError(f"search.method must be 'auto', 'adam' or 'cma', got {v!r}")
            continue
        _number(v, f"search.{k}")
        count = isinstance(getattr(SearchConfig, k), int)
        if count and (not isinstance(v, int) or abs(v) > MAX_SEARCH_COUNT):
            raise ValueError(f"search.{k} must be an integer of at most {MAX_SEARCH_COUNT}, got {v!r}")
    search = replace(SearchConfig(), **s)
    if search.screen < 1 or search.starts < 1 or search.iterations < 0 or search.batch < 1:
        raise ValueError("search: screen, starts and batch must be >= 1 and iterations >= 0")
    if search.cma_evals < 1 or not 0 < search.cma_sigma <= 2 or not 0 < search.lr <= 10:
        raise ValueError("search: cma_evals must be >= 1, cma_sigma in (0, 2] and lr in (0, 10]")
    if search.min_separation < 0 or search.secondary_weight < 0 or search.edge_weight < 0:
        raise ValueError("search: min_separation, secondary_weight and edge_weight must be >= 0")
    if not 0 <= search.edge_start < 1:
        raise ValueError(f"search.edge_start must be in [0, 1), got {search.edge_start}")
    return search


def spec_from_dict(d: Any) -> InverseSpec:
    """A ``InverseSpec`` from its JSON form; ValueError naming the bad key.

    {"targets": {metric: {"value": nm, "tol": nm} | nm}, "step": int, "fixed": {control: raw},
     "bounds": {control: [low, high]}, "secondary": {"metric": m, "goal": "min" | "max"}, "k": int,
     "search": {SearchConfig fields}}. A bare number as a target takes the default tolerance
     (depth 5 nm, widths 3 nm, mask loss 2 nm, bowing 2 nm).
    """
    if not isinstance(d, dict):
        raise ValueError(f"the design spec must be a JSON object, got {type(d).__name__}")
    known = {"targets", "step", "fixed", "bounds", "secondary", "k", "search"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"unknown spec keys {unknown}; expected some of {sorted(known)}")
    raw_targets = d.get("targets")
    if not isinstance(raw_targets, dict) or not raw_targets:
        raise ValueError(
            f"targets: give at least one of {list(TARGET_METRICS)}, e.g. "
            '{"etch_depth": {"value": 100, "tol": 5}}'
        )
    targets: dict[str, Target] = {}
    for name, t in raw_targets.items():
        if name not in TARGET_METRICS:
            raise ValueError(f"targets: unknown metric {name!r}; expected one of {list(TARGET_METRICS)}")
        if isinstance(t, dict):
            extra = sorted(set(t) - {"value", "tol"})
            if extra or "value" not in t:
                raise ValueError(f'targets.{name}: expected {{"value": nm, "tol": nm}}, got {t!r}')
            value = check_target(name, t["value"], where=f"targets.{name}.value")
            tol = check_tolerance(name, t.get("tol", DEFAULT_TOL[name]))
        else:
            value, tol = check_target(name, t), DEFAULT_TOL[name]
        targets[name] = Target(value, tol)
    step = d.get("step")
    if step is not None and (isinstance(step, bool) or not isinstance(step, int) or step < 1):
        raise ValueError(f"step must be an integer >= 1 (a state index; default the horizon), got {step!r}")
    fixed = check_fixed(d.get("fixed") or {})
    bounds = check_bounds(d.get("bounds") or {})
    both = sorted(set(fixed) & set(bounds))
    if both:
        raise ValueError(f"{both[0]} is both fixed and bounded; give one")
    secondary = None
    sec = d.get("secondary")
    if sec is not None:
        if (
            not isinstance(sec, dict)
            or sec.get("metric") not in TARGET_METRICS
            or sec.get("goal", "min") not in ("min", "max")
        ):
            raise ValueError(
                f'secondary must be {{"metric": one of {list(TARGET_METRICS)}, "goal": '
                f'"min" | "max"}}, got {sec!r}'
            )
        secondary = (str(sec["metric"]), str(sec.get("goal", "min")))
    k = d.get("k", 3)
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= 10:
        raise ValueError(f"k (recipes to report) must be an integer in 1..10, got {k!r}")
    search = SearchConfig()
    if d.get("search") is not None:
        s = d["search"]
        fields_ = set(SearchConfig.__dataclass_fields__)
        if not isinstance(s, dict) or set(s) - fields_:
            raise ValueError(
                f"search: unknown keys {sorted(set(s) - fields_) if isinstance(s, dict) else s!r}; "
                f"expected some of {sorted(fields_)}"
            )
        search = _search_config(s)
    return InverseSpec(
        targets=targets, step=step, fixed=fixed, bounds=bounds, secondary=secondary, k=k, search=search
    )


def objective(metrics: dict[str, Any], spec: InverseSpec) -> Any:
    """Sum of squared tolerance-scaled misses plus the secondary term; works on numpy and torch (B,)."""
    total: Any = 0.0
    for name, t in spec.targets.items():
        total = total + ((metrics[name] - t.value) / t.tol) ** 2
    if spec.secondary is not None:
        m, goal = spec.secondary
        sign = 1.0 if goal == "min" else -1.0
        total = total + sign * spec.search.secondary_weight * metrics[m] / SECONDARY_SCALE_NM
    return total


def edge_term(u: Any, start: float) -> Any:
    """E(u) = sum over controls of (max(|u_j| - start, 0) / (1 - start))^2; numpy or torch (..., 14)."""
    x = abs(u) - start
    x = x.clamp(min=0.0) if hasattr(x, "clamp") else np.maximum(x, 0.0)  # torch or numpy
    return ((x / (1.0 - start)) ** 2).sum(-1)


def search_score(metrics: dict[str, Any], u: Any, spec: InverseSpec) -> Any:
    """J(u) + e * E(u) (module docstring): what a search minimizes; numpy or torch (B,)."""
    j = objective(metrics, spec)
    if not spec.search.edge_weight:
        return j
    return j + spec.search.edge_weight * edge_term(u, spec.search.edge_start)


def misses(metrics: dict[str, float], spec: InverseSpec) -> dict[str, dict[str, Any]]:
    """Per target: predicted value, error (value - target), miss beyond tolerance (0 when met), met."""
    out = {}
    for name, t in spec.targets.items():
        v = float(metrics[name])
        err = v - t.value
        out[name] = {
            "target": t.value,
            "tol": t.tol,
            "value": round(v, 3),
            "error": round(err, 3),
            "miss": round(max(abs(err) - t.tol, 0.0), 3),
            "met": bool(abs(err) <= t.tol),
        }
    return out


def spec_to_dict(spec: InverseSpec) -> dict[str, Any]:
    """The JSON form of a spec (inverse of ``spec_from_dict``)."""

    return {
        "targets": {k: {"value": t.value, "tol": t.tol} for k, t in spec.targets.items()},
        "step": spec.step,
        "fixed": dict(spec.fixed),
        "bounds": {k: list(v) for k, v in spec.bounds.items()},
        "secondary": None
        if spec.secondary is None
        else {"metric": spec.secondary[0], "goal": spec.secondary[1]},
        "k": spec.k,
        "search": asdict(spec.search),
    }
