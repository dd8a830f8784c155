"""Kinetic laws ([supp_kinetic_models]): values by hand from the catalog tables, torch vs numba, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nemsim.rules import kinetics as K
from nemsim.rules import laws

E1, E7, E8, E9, E12, E23 = 0, 6, 7, 8, 11, 22


def cos_deg(a: float) -> float:
    return math.cos(math.radians(a))


def test_constants():
    assert K.TAU_E == 0.5 and K.TAU_C == 0.05
    # P law: F(c_P) = R_P at the 60 degree maximum
    assert laws._angle_physical(1, K.C_P) == pytest.approx(K.R_P, rel=1e-4)


def test_prob_physical_by_hand(tensors):
    pm, pp, ak = tensors.prob_model, tensors.prob_params, tensors.angle_kind
    # E1: constant probability 0.55, independent of energy and angle
    assert K.prob_physical(pm[E1], pp[E1], ak[E1], 0.2, 0.3) == pytest.approx(0.55)
    # E8 (Cl+ on SiCl, P): (E_th, E_ref, p0) = (35, 100, 0.10), n = 0.5
    assert K.prob_physical(pm[E8], pp[E8], ak[E8], 300.0, 1.0) == pytest.approx(0.10, rel=1e-5)
    x = (60 - 35) / (100 - 35)
    assert K.prob_physical(pm[E8], pp[E8], ak[E8], 60.0, 1.0) == pytest.approx(0.10 * math.sqrt(x), rel=1e-5)
    # at the 60 degree peak the P factor is R_P = 5
    assert K.prob_physical(pm[E8], pp[E8], ak[E8], 60.0, 0.5) == pytest.approx(0.5 * math.sqrt(x), rel=1e-4)
    assert K.prob_physical(pm[E8], pp[E8], ak[E8], 30.0, 1.0) == 0.0  # below threshold
    assert K.prob_physical(pm[E8], pp[E8], ak[E8], 300.0, -0.2) == 0.0  # from behind
    # E9 (Cl+ on SiCl, C): p0 = 0.20; flat below 45 degrees, then proportional to cos / cos 45
    assert K.prob_physical(pm[E9], pp[E9], ak[E9], 300.0, cos_deg(30)) == pytest.approx(0.20)
    assert K.prob_physical(pm[E9], pp[E9], ak[E9], 300.0, cos_deg(60)) == pytest.approx(
        0.20 * 0.5 / cos_deg(45), rel=1e-6
    )
    # deposition events have no probability model
    assert K.prob_physical(tensors.prob_model[E23], pp[E23], 0, 300.0, 1.0) == 0.0


def test_yield_physical_by_hand(tensors):
    ym, yp = tensors.yield_model, tensors.yield_params
    # E7: Yamamura (25 eV, 60 deg, 2.2, 1.2): ~1 at normal incidence, Y_max/Y0 at 60 degrees
    assert K.yield_physical(ym[E7], yp[E7], 300.0, 1.0) == pytest.approx(1.0)
    assert K.yield_physical(ym[E7], yp[E7], 300.0, 0.5) == pytest.approx(2.2 / 1.2, rel=1e-4)
    assert K.yield_physical(ym[E7], yp[E7], 20.0, 1.0) == 0.0
    assert K.yield_physical(ym[E7], yp[E7], 300.0, 0.0) == 0.0
    assert K.yield_physical(ym[E9], yp[E9], 300.0, 0.7) == 1.0  # constant unit yield


def test_p_law_shape():
    angles = np.arange(0.0, 90.0, 5.0)
    f = np.array([laws._angle_physical(1, cos_deg(a)) for a in angles])
    peak = angles[np.argmax(f)]
    assert peak == 60.0
    assert f[0] == pytest.approx(1.0)
    assert np.all(np.diff(f[angles <= 60]) > 0) and np.all(np.diff(f[angles >= 60]) < 0)
    assert laws._angle_physical(1, cos_deg(89.9)) < 1e-3
    # torch smooth version has the same shape away from grazing incidence
    c = torch.tensor([[cos_deg(a) for a in angles[:-2]]], dtype=torch.float64)
    ft = K.angle_factor(c, torch.ones(c.shape[1], dtype=torch.long))
    np.testing.assert_allclose(ft[0].numpy(), f[:-2], rtol=1e-2)  # gate sigmoid((c-eps)/tau_c)


@pytest.mark.parametrize("e", [6, 7, 8, 10, 11, 14, 17, 20, 21])
def test_torch_matches_numba_far_from_thresholds(tensors, e):
    """Smooth torch laws with physical energies equal the hard numba laws away from thresholds
    (the probability up to the validity gate G0 = sigmoid(p0/tau_E), whose hard limit is 1)."""
    energies = [90.0, 200.0, 480.0]
    angles = [0.0, 15.0, 60.0, 75.0]  # away from the C law's 45 degree switch
    E = torch.tensor([[en] for en in energies for _ in angles], dtype=torch.float64)  # (B, 1)
    c = torch.tensor([[cos_deg(a)] for _ in energies for a in angles], dtype=torch.float64)
    idx = slice(e, e + 1)
    pp = torch.from_numpy(tensors.prob_params[idx])
    p_t = K.probability(E, c, torch.from_numpy(tensors.prob_model[idx]), pp,
                        torch.from_numpy(tensors.angle_kind[idx]))  # fmt: skip
    y_t = K.yield_factor(E, c, torch.from_numpy(tensors.yield_model[idx]),
                         torch.from_numpy(tensors.yield_params[idx]))  # fmt: skip
    g0 = 1.0 / (1.0 + math.exp(-tensors.prob_params[e, 2] / K.TAU_E))
    for b in range(E.shape[0]):
        en, cc = float(E[b, 0]), float(c[b, 0])
        p_n = K.prob_physical(tensors.prob_model[e], tensors.prob_params[e], tensors.angle_kind[e], en, cc)
        y_n = K.yield_physical(tensors.yield_model[e], tensors.yield_params[e], en, cc)
        assert float(p_t[b, 0]) / g0 == pytest.approx(p_n, rel=1e-2, abs=1e-9)
        assert float(y_t[b, 0]) == pytest.approx(y_n, rel=1e-2, abs=1e-9)


def test_primary_terms_by_hand(tensors):
    u = torch.zeros(1, 14, dtype=torch.float64)
    u[0, 1], u[0, 3], u[0, 5], u[0, 8] = 0.3, -0.4, 0.7, 0.2  # flux_cl+, flux_cl, angle_cl+, energy_mean_cl+
    f, p, y = K.primary_terms(u, tensors)
    sp = lambda v: math.log1p(math.exp(v))  # noqa: E731
    sig = lambda v: 1.0 / (1.0 + math.exp(-v))  # noqa: E731
    # E1: f = softplus(u_flux_cl), p = 0.55, Y = 1
    assert float(f[0, E1]) == pytest.approx(sp(-0.4))
    assert float(p[0, E1] * y[0, E1]) == pytest.approx(0.55)
    # E9: C law with the effective cosine and normalized thresholds
    k = sp(0.7)
    c = (k + 1) / (k + 2 + K.EPS)
    energy = sp(0.2)
    e_th, e_ref = 2 * (10 - 160) / 340 - 1, 2 * (100 - 160) / 340 - 1
    x = min(max((energy - e_th) / (e_ref - e_th + K.EPS), 0.0), 1.0)
    w = sig((math.radians(45) - math.acos(c)) / K.TAU_C)
    f_c = (w + (1 - w) * c / math.cos(math.radians(45))) * sig((c - K.EPS) / K.TAU_C)
    expect = 0.20 * x**0.5 * f_c * sig((energy - e_th) / K.TAU_E) * sig(0.20 / K.TAU_E)
    assert float(p[0, E9]) == pytest.approx(expect, rel=1e-9)
    assert float(f[0, E9]) == pytest.approx(sp(0.3))
    # E7: Yamamura multiplier at the effective cosine
    c_max, ratio = 0.5, 2.2 / 1.2
    q = -math.log(ratio) / (math.log(c_max) + 1 - c_max + K.EPS)
    e_th = 2 * (25 - 160) / 340 - 1  # 25 eV in normalized energy coordinates
    y_expect = c ** (-q) * math.exp(-q * c_max * (1 / c - 1)) * sig((energy - e_th) / 0.5)
    y_expect *= sig((c - K.EPS) / K.TAU_C)
    assert float(y[0, E7]) == pytest.approx(y_expect, rel=1e-9)
    # deposition events: no primary terms
    assert float(f[0, 22:].abs().sum()) == 0.0


def test_pool_and_dependencies(tensors):
    u = torch.linspace(-1, 1, 14, dtype=torch.float64).unsqueeze(0)
    f, p, y = K.primary_terms(u, tensors)
    lam = f * p * y
    pool = K.product_pool(lam, y, tensors)
    # by hand: SiCl pool = fixed sources + yield-scaled sources
    sicl = 5
    expect = sum(
        float(lam[0, e]) * (float(y[0, e]) if tensors.src_is_yield[e, sicl] else tensors.w_src[e, sicl])
        for e in range(37)
    )
    assert float(pool[0, sicl]) == pytest.approx(expect)
    dep = K.dependency_base(pool, tensors)
    assert float(dep[0, E23]) == pytest.approx(0.02 * expect)
    assert float(dep[0, :22].abs().sum()) == 0.0
    total = K.formula_intensities(u, tensors)
    torch.testing.assert_close(total, lam + dep)
    assert (total >= 0).all()
    torch.testing.assert_close(K.base_intensity(u, tensors), lam)


def test_gradients_finite(tensors):
    gen = torch.Generator().manual_seed(0)
    u = (torch.rand(8, 14, generator=gen) * 6 - 3).requires_grad_(True)
    lam = K.formula_intensities(u, tensors.torch_buffers())
    assert lam.shape == (8, 37) and torch.isfinite(lam).all()
    lam.sum().backward()
    assert torch.isfinite(u.grad).all() and u.grad.abs().sum() > 0
