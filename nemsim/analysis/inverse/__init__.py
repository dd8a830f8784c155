"""Inverse design: recipes (constant controls) whose predicted profile meets target metrics.

Question answered: "which controls give a 100-nm-deep hole with a 30-nm bottom and the least mask loss?"
The surrogate is differentiable and a rollout is cheap, so the search runs on it; the reported metrics are
the exact ones of a plain rollout, with conformal intervals and a distance-to-training-data flag.

Modules, in import order (each imports only the ones above it):
  ``spec``              what to design (``InverseSpec``), its JSON form, the objective;
  ``context``           the loaded checkpoint (``InverseContext``), differentiable rollouts to a state;
  ``surrogate_search``  the search on the surrogate (screening, Adam or CMA-ES, re-evaluation);
  ``verify``            the simulator's metrics of a recipe against its targets; each recipe's verdict;
  ``refine``            simulator-corrected rounds (the simulator inside the design loop);
  ``run``               the CLI's whole design in one process; ``report`` its readable table.
"""

from nemsim.analysis.inverse.context import InverseContext, load_inverse_context, rollout_to, simulator_config
from nemsim.analysis.inverse.refine import (
    REFINE_WITH_VERIFY,
    RefineConfig,
    refine_config_from_dict,
    refine_with_simulator,
)
from nemsim.analysis.inverse.report import format_result
from nemsim.analysis.inverse.run import run_inverse
from nemsim.analysis.inverse.spec import (
    DEFAULT_TOL,
    MIN_TOL_NM,
    TARGET_METRICS,
    InverseSpec,
    Progress,
    SearchCancelled,
    SearchConfig,
    Target,
    check_bounds,
    check_fixed,
    check_target,
    check_targets,
    check_tolerance,
    misses,
    objective,
    spec_from_dict,
    spec_to_dict,
    target_range,
)
from nemsim.analysis.inverse.surrogate_search import LocalRegion, search
from nemsim.analysis.inverse.verify import (
    VERDICTS,
    Simulate,
    SimulateMetrics,
    SimulationSkipped,
    interval_inside,
    label_recipes,
    simulated_metrics,
    verify_recipe,
    verify_recipes,
)

__all__ = [
    "DEFAULT_TOL",
    "MIN_TOL_NM",
    "REFINE_WITH_VERIFY",
    "TARGET_METRICS",
    "VERDICTS",
    "InverseContext",
    "InverseSpec",
    "LocalRegion",
    "Progress",
    "RefineConfig",
    "SearchCancelled",
    "SearchConfig",
    "Simulate",
    "SimulateMetrics",
    "SimulationSkipped",
    "Target",
    "check_bounds",
    "check_fixed",
    "check_target",
    "check_targets",
    "check_tolerance",
    "format_result",
    "interval_inside",
    "label_recipes",
    "load_inverse_context",
    "misses",
    "objective",
    "refine_config_from_dict",
    "refine_with_simulator",
    "rollout_to",
    "run_inverse",
    "search",
    "simulated_metrics",
    "simulator_config",
    "spec_from_dict",
    "spec_to_dict",
    "target_range",
    "verify_recipe",
    "verify_recipes",
]
