"""``run_inverse``: the CLI's whole inverse design in one process (search, then verification or the
simulator-corrected rounds with an in-process simulator)."""

from __future__ import annotations

from typing import Any

import numpy as np

from nemsim.analysis.inverse.context import InverseContext, simulator_config
from nemsim.analysis.inverse.refine import RefineConfig, refine_with_simulator
from nemsim.analysis.inverse.spec import InverseSpec, check_targets, spec_to_dict
from nemsim.analysis.inverse.surrogate_search import search
from nemsim.analysis.inverse.verify import label_recipes, simulated_metrics, verify_recipes


def run_inverse(
    ctx: InverseContext,
    spec: InverseSpec,
    *,
    seed: int = 0,
    verify: bool = False,
    verify_top: int = 1,
    sim_seed: int = 1,
    progress: bool = False,
    refine: RefineConfig | None = None,
) -> dict[str, Any]:
    """Search (and with ``verify`` simulate the top recipes in-process); the CLI's entry point.

    With ``refine`` (a ``RefineConfig``) the simulator is used inside the
    design loop instead (simulator-corrected rounds; implies ``verify``, and ``verify_top`` is the
    config's). Each recipe says whether the surrogate predicts it or the simulator confirmed it
    (``label_recipes``). ValueError if a target or tolerance lies outside its physical range in the
    checkpoint's scene (``check_targets``).
    """
    check_targets(spec.targets, ctx.scene)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=100, desc="inverse design", unit="%", dynamic_ncols=True, leave=False)

    def report(f: float, msg: str) -> None:
        if bar is not None:
            bar.n = int(100 * f)
            bar.set_postfix_str(msg)
            bar.refresh()

    from nemsim.sim import run_trajectory

    config = simulator_config(ctx.loaded)

    def simulate(raw: np.ndarray, steps: int) -> np.ndarray:
        rng = np.random.default_rng(sim_seed)
        return run_trajectory(ctx.scene, ctx.loaded.rules, raw, rng, config, n_transitions=steps).states

    try:
        if refine is not None:
            result = refine_with_simulator(
                ctx,
                spec,
                simulated_metrics(simulate, ctx.scene),
                refine=refine,
                seed=seed,
                sim_seed=sim_seed,
                on_progress=report,
            )
        else:
            result = search(ctx, spec, seed=seed, on_progress=report)
    finally:
        if bar is not None:
            bar.close()
    if verify and refine is None:
        result["verification"] = {
            "seed": sim_seed,
            "recipes": verify_recipes(result, spec, ctx.scene, simulate, verify_top),
        }
    result["spec"] = spec_to_dict(spec)
    return label_recipes(result, spec)
