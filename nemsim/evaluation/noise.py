"""Monte Carlo noise floor of the simulator (``nemsim bench noise``).

The Avg RMSE [eq:supp_avg_rmse] between two runs of the same controls
with different seeds, over t = 1..100, computed with ``nemsim.evaluation.metrics`` exactly as for model
predictions; a surrogate cannot be expected to beat it.
"""

from __future__ import annotations

import numpy as np

from nemsim.evaluation.metrics import rmse_per_step
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene
from nemsim.sim.config import SimConfig
from nemsim.sim.events import build_event_tables
from nemsim.sim.process import run_trajectory


def bench_noise(
    scene: Scene,
    rules: RuleTensors,
    design: np.ndarray,
    config: SimConfig | None = None,
    seeds: tuple[int, int] = (1, 2),
) -> dict:
    """Avg and final RMSE between two seeds of the same controls, per case and over the cases.

    Args: design (n, 14) raw controls; seeds: the two base seeds (case i uses default_rng([seed, i])).
    """
    config = (config or SimConfig()).resolved(scene)
    tables = build_event_tables(rules, config)
    runs = []
    for s in seeds:
        states = [
            run_trajectory(scene, rules, u, np.random.default_rng([s, i]), config, tables=tables).states
            for i, u in enumerate(design)
        ]
        runs.append(np.stack(states))  # (n, T+1, 2, D, H, W)
    a, b = runs[0][:, 1:], runs[1][:, 1:]  # t = 1..100
    per_case = [rmse_per_step(a[i : i + 1], b[i : i + 1]) for i in range(len(design))]
    r_t = rmse_per_step(a, b)
    return {
        "scene": scene.name,
        "n_cases": len(design),
        "seeds": list(seeds),
        "avg_rmse": float(r_t.mean()),
        "final_rmse": float(r_t[-1]),
        "per_case_avg_rmse": [float(r.mean()) for r in per_case],
        "per_channel_avg_rmse": [float(rmse_per_step(a[:, :, c], b[:, :, c]).mean()) for c in range(2)],
    }
