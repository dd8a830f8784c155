"""Verification: the simulator's exact metrics of a recipe against its targets and its intervals.

The simulator is a caller-supplied function (in-process for the CLI, child processes in the service, cached
runs in the benchmark, a fake in tests), so this module never runs it itself.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from nemsim.analysis.inverse.spec import InverseSpec, Progress, misses
from nemsim.controls import CONTROL_NAMES
from nemsim.geometry.profile import profile_metrics_batch


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
