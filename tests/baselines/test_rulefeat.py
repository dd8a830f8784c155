"""RuleFeat (eq:rulefeat) against a hand computation for one primary and one deposition event."""

from __future__ import annotations

import numpy as np
import torch

from nemsim.baselines.rulefeat import RuleFeat


def _softplus(v: float) -> float:
    return float(np.log1p(np.exp(v)))


def test_rulefeat_hand_computation(rules):
    names = list(rules.names)
    E, M = rules.alpha0.shape
    rf = RuleFeat(rules)
    assert rf.dim == E * (1 + M) == 148
    assert sum(p.numel() for p in rf.parameters()) == 0
    u = torch.linspace(-0.9, 0.8, 14, dtype=torch.float32)[None]  # (1, 14)
    feat = rf(u)[0].double().numpy()  # (148,)

    # primary: Cl on Si -> SiCl, constant probability and yield, supply = softplus(u[flux_cl])
    e = names.index("Cl_on_Si_to_SiCl")
    assert rules.is_primary[e] and rules.prob_model[e] == 0 and rules.yield_model[e] == 0
    lam_e = _softplus(float(u[0, rules.ctrl_idx[e, 0]])) * rules.prob_params[e, 0] * rules.yield_params[e, 0]
    np.testing.assert_allclose(feat[e], lam_e, rtol=1e-5)
    np.testing.assert_allclose(feat[E + M * e: E + M * (e + 1)], lam_e * rules.alpha0[e], rtol=1e-5)

    # deposition: SiCl deposition on Si = s_dep * pool[SiCl], pool = sum over primary events of
    # lambda_e' * w_src[e', SiCl] (times the yield where the source is yield-scaled)
    from nemsim.rules.kinetics import primary_terms

    d = names.index("SiCl_dep_on_Si")
    assert not rules.is_primary[d]
    q = int(np.flatnonzero(rules.w_sink[d])[0])  # sunk species (SiCl)
    f, p, y = (t[0].double().numpy() for t in primary_terms(u, rules))
    pool_q = 0.0
    for k in range(E):
        if not rules.is_primary[k]:
            continue
        xi = rules.w_src[k, q] * (y[k] if rules.src_is_yield[k, q] else 1.0)
        pool_q += f[k] * p[k] * y[k] * xi
    lam_d = rules.s_dep[d] * rules.w_sink[d, q] * pool_q
    assert lam_d > 0
    np.testing.assert_allclose(feat[d], lam_d, rtol=1e-5)
    np.testing.assert_allclose(feat[E + M * d: E + M * (d + 1)], lam_d * rules.alpha0[d], rtol=1e-5)


def test_rulefeat_deterministic_and_control_dependent(rules):
    rf = RuleFeat(rules)
    u = torch.zeros(2, 14)
    u[1, 3] = 0.7  # more Cl flux in the second row
    a, b = rf(u), rf(u)
    assert torch.equal(a, b) and a.shape == (2, 148)
    assert not torch.equal(a[0], a[1])
