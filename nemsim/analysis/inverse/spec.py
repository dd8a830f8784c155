"""The inverse-design spec: targets, held and bounded controls, the objective and its JSON form.

A spec asks for recipes (constant controls) whose profile metrics at one state index meet target values
within tolerances. The objective a search minimizes is

    J(u) = sum over targets of ((m(u) - value) / tol)^2  +  w * (+-) m_s(u) / 10 nm,

the second term for an optional secondary goal (``secondary_weight`` w; sign + to minimize metric m_s,
- to maximize). A target is met when |m - value| <= tol.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

import numpy as np

from nemsim.controls import CONTROL_SPECS, N_CONTROLS, check_admissible, control_index, from_normalized
from nemsim.geometry.soft_profile import SOFT_METRICS

TARGET_METRICS = SOFT_METRICS  # etch_depth, top_width, bottom_width, bowing, mask_loss
DEFAULT_TOL = {"etch_depth": 5.0, "top_width": 3.0, "bottom_width": 3.0, "mask_loss": 2.0, "bowing": 2.0}
SECONDARY_SCALE_NM = 10.0
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


def _control(name: Any, where: str) -> int:
    if not isinstance(name, str):
        raise ValueError(f"{where}: control names are strings, got {name!r}")
    try:
        return control_index(name)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


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
            value = _number(t["value"], f"targets.{name}.value")
            tol = _number(t.get("tol", DEFAULT_TOL[name]), f"targets.{name}.tol")
        else:
            value, tol = _number(t, f"targets.{name}"), DEFAULT_TOL[name]
        if tol <= 0:
            raise ValueError(f"targets.{name}.tol must be > 0 nm, got {tol:g}")
        targets[name] = Target(value, tol)
    step = d.get("step")
    if step is not None and (isinstance(step, bool) or not isinstance(step, int) or step < 1):
        raise ValueError(f"step must be an integer >= 1 (a state index; default the horizon), got {step!r}")
    fixed: dict[str, float] = {}
    for name, v in (d.get("fixed") or {}).items():
        j = _control(name, "fixed")
        fixed[name] = _number(v, f"fixed.{name}")
        if CONTROL_SPECS[j].kind == "int" and fixed[name] != round(fixed[name]):
            raise ValueError(f"fixed.{name} = {fixed[name]:g} is not an integer (cosine-power exponent)")
    bounds: dict[str, tuple[float, float]] = {}
    for name, b in (d.get("bounds") or {}).items():
        _control(name, "bounds")
        if not isinstance(b, list | tuple) or len(b) != 2:
            raise ValueError(f"bounds.{name} must be [low, high] in physical units, got {b!r}")
        lo, hi = _number(b[0], f"bounds.{name}[0]"), _number(b[1], f"bounds.{name}[1]")
        if not lo < hi:
            raise ValueError(f"bounds.{name}: need low < high, got [{lo:g}, {hi:g}]")
        if name in fixed:
            raise ValueError(f"{name} is both fixed and bounded; give one")
        bounds[name] = (lo, hi)
    probe = np.asarray(from_normalized(np.zeros(N_CONTROLS)), dtype=np.float64)
    for name, v in fixed.items():
        probe[control_index(name)] = v
    bad = check_admissible(probe)
    for name, (lo, _) in bounds.items():
        if lo < CONTROL_SPECS[control_index(name)].phys_min:
            bad.append(f"bounds.{name} low {lo:g} is below the physical minimum")
    if bad:
        raise ValueError(f"physically impossible input: {bad[0]}")
    for name, (_, hi) in bounds.items():
        if not math.isfinite(hi):
            raise ValueError(f"bounds.{name} high must be finite")
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
        search = replace(search, **s)
        if search.method not in ("auto", "adam", "cma"):
            raise ValueError(f"search.method must be 'auto', 'adam' or 'cma', got {search.method!r}")
        if search.screen < 1 or search.starts < 1 or search.iterations < 0 or search.batch < 1:
            raise ValueError("search: screen, starts and batch must be >= 1 and iterations >= 0")
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
