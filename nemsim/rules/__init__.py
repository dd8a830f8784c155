"""Event Rules Library: schema, compiler, kinetic laws, perturbations.

[supp_rule_schema], [supp_event_catalog], [supp_kinetic_models], [supp_mechanism_mapping],
[supp_rule_robustness]. Typical use::

    from nemsim.rules import load_rules, compile_rules
    rules = compile_rules(load_rules())          # the repository's rules/cl_si.yaml
    lam = kinetics.formula_intensities(u_norm, rules)

``laws`` (the simulator's numba laws, torch-free), ``kinetics`` (their differentiable torch forms) and
``perturb`` are imported on demand (``nemsim.rules.kinetics``).
"""

from nemsim.rules.compile import RuleTensors, compile_rules
from nemsim.rules.schema import EventRule, RulesError, RulesSpec, load_rules, parse_rules
from nemsim.rules.vocab import FAMILIES, PROJECTILES, TARGETS

__all__ = [
    "FAMILIES",
    "PROJECTILES",
    "TARGETS",
    "EventRule",
    "RuleTensors",
    "RulesError",
    "RulesSpec",
    "compile_rules",
    "load_rules",
    "parse_rules",
]
