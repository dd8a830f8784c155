"""RuleFeat: the deterministic rule-derived feature vector of the knowledge-augmented baselines
([supp_rulefeat], eq:rulefeat).

  f_rule(u) = [ lambda^RF (E) ; vec(lambda^RF[:, None] * alpha0) (E*M) ]  in R^{E(1+M)} = R^148 for 37 events,

where lambda^RF = ``nemsim.rules.kinetics.formula_intensities(u_norm, rules, kinetics)``: the rule-formula
primary
intensities f p Y, and for product-dependent deposition events d_e p_stick pool_q evaluated on the Product
Pool of those base intensities (the pool itself is not returned, as the paper prescribes). alpha0 is the
static event-mechanism prior of the compiled library; vec() is row-major (event-major: e0m0, e0m1, e0m2,
e1m0, ...), the events in library order.

``kinetics``: "paper" (default, the paper's normalized energy coordinates) or "physical" (physical eV and
mean incidence cosines with energy-spread-smoothed thresholds, as the simulator evaluates the laws; see
``nemsim.rules.kinetics``).

No trainable parameters and no randomness; recomputed on every forward pass from u. The compiled rules are
held as fixed buffers (``nemsim.model.rule_buffers.RuleBuffers``), so they move with the model and are saved
with it. RuleFeat does not see the state.
"""

from __future__ import annotations

import torch
from torch import nn

from nemsim.model.rule_buffers import RuleBuffers
from nemsim.rules.kinetics import Kinetics, check_kinetics, formula_intensities

RULEFEAT_DIM = 148  # 37 + 37 * 3 for the paper's library


class RuleFeat(nn.Module):
    """u (B, 14) normalized -> f_rule (B, E (1 + M)) float32."""

    def __init__(self, rules, kinetics: Kinetics = "paper") -> None:
        super().__init__()
        self.kinetics = check_kinetics(kinetics)
        self.rules = rules if isinstance(rules, RuleBuffers) else RuleBuffers(rules)
        E, M = self.rules.alpha0.shape
        self.dim = int(E * (1 + M))

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        # a plain dict of the buffers: the form every kinetics entry point accepts
        lam = formula_intensities(u, self.rules.torch_buffers(), self.kinetics)  # (B, E)
        alpha0 = self.rules.alpha0.to(lam.dtype)  # (E, M)
        g = lam[:, :, None] * alpha0[None]  # (B, E, M)
        return torch.cat([lam, g.flatten(1)], dim=1).to(torch.float32)  # (B, E (1 + M))


def prior_projection(
    rules, hidden: int, out: int, model: str, kinetics: Kinetics = "paper"
) -> tuple[RuleFeat, nn.Sequential]:
    """The +Prior branch shared by CNO+Prior and DeepONet+Prior: RuleFeat (148-d, no parameters) and its
    148 -> hidden -> out GELU projection ([supp_rulefeat]). ``model`` names the caller in the error."""
    if rules is None:
        raise ValueError(f"{model}+Prior (rulefeat=True) needs the compiled rules")
    feat = RuleFeat(rules, kinetics)
    return feat, nn.Sequential(nn.Linear(feat.dim, hidden), nn.GELU(), nn.Linear(hidden, out))
