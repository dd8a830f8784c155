"""Simulator speed benchmark (``nemsim bench sim``); the Monte Carlo noise floor is
``bench.noise`` (it scores with the evaluation metrics).

Speed: median wall time and CPU time per 101-state trajectory and primary particles per second, on the
first design cases, one core, after a JIT warm-up (a one-transition run of every scene). Wall time on a
shared machine includes waiting for the CPU, so the CPU time (``time.process_time``) is reported too.
"""

from __future__ import annotations

import logging
import statistics
import time

import numpy as np

from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene
from nemsim.sim.config import SimConfig
from nemsim.sim.events import build_event_tables
from nemsim.sim.process import run_trajectory

log = logging.getLogger(__name__)


def warm_up(scene: Scene, rules: RuleTensors, config: SimConfig, controls_raw: np.ndarray) -> None:
    """Compile (or load from cache) every kernel by simulating one transition."""
    run_trajectory(scene, rules, controls_raw, np.random.default_rng(0), config, n_transitions=1)


def bench_speed(
    scene: Scene, rules: RuleTensors, design: np.ndarray, config: SimConfig | None = None, seed: int = 0
) -> dict:
    """Time full trajectories of the design rows ``design`` (n, 14) on ``scene``.

    Returns: dict with per-case rows and the medians (wall_s, cpu_s, primaries, primaries_per_s).
    """
    config = (config or SimConfig()).resolved(scene)
    tables = build_event_tables(rules, config)
    warm_up(scene, rules, config, design[0])
    rows = []
    for i, u in enumerate(design):
        c0 = time.process_time()
        res = run_trajectory(scene, rules, u, np.random.default_rng([seed, i]), config, tables=tables)
        cpu = time.process_time() - c0
        prim = res.counters["primary"]
        rows.append({"case": i, "wall_s": res.wall_s, "cpu_s": cpu, "primaries": prim,
                     "primaries_per_s": prim / max(res.wall_s, 1e-9),
                     "primaries_per_cpu_s": prim / max(cpu, 1e-9)})  # fmt: skip
        log.info("%s case %d: %.2f s wall, %.2f s cpu, %d primaries", scene.name, i, res.wall_s, cpu, prim)
    med = {k: statistics.median(r[k] for r in rows) for k in rows[0] if k != "case"}
    return {"scene": scene.name, "n_cases": len(rows), "cases": rows, "median": med,
            "capacity": config.capacity}  # fmt: skip

