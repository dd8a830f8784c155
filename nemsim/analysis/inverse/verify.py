"""Verification: the simulator's exact metrics of a recipe against its targets and its intervals, and each
reported recipe's verdict.

The simulator is a caller-supplied function (in-process for the CLI, child processes in the service, cached
runs in the benchmark, a fake in tests), so this module never runs it itself.

A recipe's verdict (``label_recipes``) keeps what the surrogate predicts apart from what the simulator
showed: ``confirmed`` (the simulator met every target, in its confirmation run too when one was made),
``simulator_miss`` (simulated, and a target missed), ``predicted`` (not simulated; the surrogate's metrics
meet every target) or ``predicted_miss`` (not simulated; they miss one). A prediction comes with
``intervals_within_tolerance``: per interval level, whether the interval lies inside every tolerance band.
Where it does not (a 90 % depth interval 20 nm wide against +-5 nm), a prediction that meets the targets is
a guess until the simulator runs it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from nemsim.analysis.inverse.spec import InverseSpec, Progress, misses
from nemsim.controls import CONTROL_NAMES
from nemsim.geometry.profile import profile_metrics_batch

VERDICTS = {  # label_recipes' verdicts and how the CLI's table and the page word them
    "confirmed": "confirmed by the simulator",
    "simulator_miss": "missed a target in the simulator",
    "predicted": "predicted to meet every target (not simulated)",
    "predicted_miss": "predicted to miss a target",
}


class SimulationSkipped(Exception):
    """The simulator declined a recipe (e.g. beyond a server's work limit); the message says why."""


Simulate = Callable[[np.ndarray, int], np.ndarray]  # (raw (14,), steps) -> states (steps + 1, 2, D, H, W)
SimulateMetrics = Callable[[np.ndarray, int], dict[str, float]]  # (raw (14,), step) -> metrics at step, nm


def simulated_metrics(simulate: Simulate, scene: Any) -> SimulateMetrics:
    """The exact profile metrics at the target step of a simulator run (what verification compares)."""

    def metrics_at(raw: np.ndarray, step: int) -> dict[str, float]:
        states = simulate(raw, step)
        return {k: float(v[step]) for k, v in profile_metrics_batch(states, scene).items()}

    return metrics_at


def verify_recipe(
    rec: dict[str, Any], spec: InverseSpec, step: int, simulate: SimulateMetrics, rank: int = 1
) -> dict[str, Any]:
    """Simulate one recipe of a result and compare the simulator's metrics at ``step`` with the targets and
    with the recipe's predicted intervals."""
    raw = np.array([rec["controls"][n] for n in CONTROL_NAMES], dtype=np.float64)
    t0 = time.perf_counter()
    achieved = simulate(raw, step)
    sim_s = time.perf_counter() - t0
    inside = {}
    for level, per in (rec.get("intervals") or {}).items():
        inside[level] = {
            m: bool((lo is None or achieved[m] >= lo) and (hi is None or achieved[m] <= hi))
            for m, (lo, hi) in per.items()
        }
    tmiss = misses(achieved, spec)
    return {
        "rank": rec.get("rank", rank),
        "achieved": {k: round(float(v), 3) for k, v in achieved.items()},
        "targets": tmiss,
        "met": all(v["met"] for v in tmiss.values()),
        "within_intervals": inside,
        "simulator_s": round(sim_s, 3),
    }


def verify_recipes(
    result: dict[str, Any],
    spec: InverseSpec,
    scene: Any,
    simulate: Simulate,
    top: int = 1,
    on_progress: Progress | None = None,
) -> list[dict[str, Any]]:
    """Simulate the ``top`` recipes of a result and compare the simulator's exact metrics at the target step
    with the targets and with the predicted intervals (``verify_recipe``)."""
    out = []
    step = int(result["step"])
    recipes = result["recipes"][:top]
    metrics_at = simulated_metrics(simulate, scene)
    for i, rec in enumerate(recipes):
        if on_progress is not None:
            on_progress(i / len(recipes), f"simulating recipe {i + 1}/{len(recipes)}")
        out.append(verify_recipe(rec, spec, step, metrics_at, i + 1))
    return out


def interval_inside(rec: dict[str, Any], spec: InverseSpec, level: float) -> bool:
    """Whether the recipe's interval at ``level`` lies inside every target's tolerance band. The interval
    at level 0 is the prediction itself; at level 1 it is unbounded (never inside)."""
    if level >= 1:
        return False
    per: dict[str, Any] | None
    if level == 0:
        per = {m: (v, v) for m, v in rec["predicted"].items()}
    else:
        per = (rec.get("intervals") or {}).get(f"{level:g}")
    if per is None:
        return False
    for m, t in spec.targets.items():
        lo, hi = per.get(m, (None, None))
        if lo is None or hi is None or lo < t.value - t.tol or hi > t.value + t.tol:
            return False
    return True


def label_recipes(result: dict[str, Any], spec: InverseSpec) -> dict[str, Any]:
    """``result`` with each recipe's ``verdict`` and ``intervals_within_tolerance`` (module docstring).

    A recipe of a plain verification (``result["verification"]``'s entries by rank) gets the simulator's
    fields a simulator-corrected design gives its recipes (``verified_by``, ``simulated``,
    ``simulated_targets``, ``simulator_met``); once a result has a verification, every recipe says
    ``verified_by``. Idempotent; the recipes are updated in place.
    """
    ver = result.get("verification")
    plain = {v["rank"]: v for v in (ver or {}).get("recipes", []) if "round" not in v}
    for r in result["recipes"]:
        entry = plain.get(r["rank"])
        if entry is not None:
            r.update(verified_by="simulator", simulated=entry["achieved"],
                     simulated_targets=entry["targets"], simulator_met=entry["met"])
        elif ver is not None:
            r.setdefault("verified_by", "surrogate")
        if r.get("verified_by") == "simulator":
            met = r["simulator_met"] and r.get("confirmed", True)
            r["verdict"] = "confirmed" if met else "simulator_miss"
        else:
            r["verdict"] = "predicted" if all(t["met"] for t in r["targets"].values()) else "predicted_miss"
        r["intervals_within_tolerance"] = {
            level: interval_inside(r, spec, float(level)) for level in (r.get("intervals") or {})
        }
    return result
