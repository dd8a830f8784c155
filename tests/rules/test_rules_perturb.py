"""Perturbed libraries ([supp_rule_robustness]): pure, deterministic per seed, different across seeds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nemsim.rules import kinetics as K
from nemsim.rules.perturb import (
    PERTURBATION_KINDS,
    event_drop,
    mechanism_shuffle,
    perturb,
    rate_yield_noise,
    structure_only,
)

ARRAYS = ("R", "phi", "psi", "alpha0", "r_mech", "w_src", "w_sink", "s_dep", "prob_params", "yield_params",
          "event_mask")  # fmt: skip


def _same(a, b) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ARRAYS) and a.sha256 == b.sha256


@pytest.mark.parametrize("kind", [k for k in PERTURBATION_KINDS if k != "none"])
def test_deterministic_and_seed_dependent(spec, tensors, kind):
    a, b, c = perturb(spec, kind, 0), perturb(tensors, kind, 0), perturb(spec, kind, 1)
    assert _same(a, b)
    assert not _same(a, c)
    assert a.sha256 != tensors.sha256 and a.perturbation == f"{kind}(seed=0)"
    for key in ARRAYS:
        assert getattr(a, key).shape == getattr(tensors, key).shape
    # the input is untouched
    assert tensors.perturbation == "none" and tensors.event_mask.sum() == 37
    lam = K.formula_intensities(torch.zeros(2, 14), a)
    assert torch.isfinite(lam).all() and (lam >= 0).all()


def test_none_and_bad_kind(spec, tensors):
    assert perturb(spec, "none", 3).sha256 == tensors.sha256
    with pytest.raises(ValueError, match="mechanism-shuffle"):
        perturb(spec, "shuffle", 0)


def test_mechanism_shuffle(tensors):
    out = mechanism_shuffle(tensors, seed=4)
    changed = np.argmax(out.alpha0, 1) != np.argmax(tensors.alpha0, 1)
    assert changed.sum() == 12
    np.testing.assert_allclose(out.alpha0.sum(1), 1.0)
    assert set(np.round(out.alpha0.ravel(), 6)) == {0.05, 0.9}
    for key in ("R", "phi", "r_mech", "w_src", "group"):
        np.testing.assert_array_equal(getattr(out, key), getattr(tensors, key))


def test_event_drop(tensors):
    out = event_drop(tensors, seed=2)
    dropped = out.event_mask == 0
    assert dropped.sum() == 12
    u = torch.rand(3, 14, generator=torch.Generator().manual_seed(1)) * 2 - 1
    lam = K.formula_intensities(u, out)
    assert float(lam[:, torch.from_numpy(dropped)].abs().sum()) == 0.0
    base = K.formula_intensities(u, tensors)
    keep = torch.from_numpy(~dropped & tensors.is_primary)
    torch.testing.assert_close(lam[:, keep], base[:, keep])


def test_rate_yield_noise(spec, tensors):
    noisy = rate_yield_noise(spec, seed=7)
    out_t = perturb(spec, "rate-noise", 7)
    assert [e.name for e in noisy.events] == [e.name for e in spec.events]
    for key in ("ctrl_idx", "group", "prob_model", "yield_model", "angle_kind", "w_sink", "src_is_yield"):
        np.testing.assert_array_equal(getattr(out_t, key), getattr(tensors, key))
    base = tensors.prob_params[:, :4]
    ratio_p = out_t.prob_params[:, :4] / np.where(base == 0, 1, base)
    nz = tensors.prob_params[:, :4] != 0
    assert (ratio_p[nz] >= 0.7 - 1e-12).all() and (ratio_p[nz] <= 1.3 + 1e-12).all()
    assert not np.allclose(out_t.prob_params, tensors.prob_params)
    assert (out_t.prob_params[out_t.prob_model == 0, 0] <= 1.0).all()
    assert (out_t.s_dep[22:] != 0.02).any() and (out_t.s_dep[22:] <= 1).all()
    np.testing.assert_array_equal(out_t.prob_params[6:22, 4], tensors.prob_params[6:22, 4])  # angle kinds


def test_structure_only(tensors):
    out = structure_only(tensors, seed=0)
    np.testing.assert_allclose(out.alpha0, 1 / 3)
    assert out.w_src.sum() == 0 and out.w_sink.sum() == 0 and out.s_dep.sum() == 0
    assert out.is_primary.all() and (out.prob_model == 0).all()
    assert not np.allclose(out.phi, tensors.phi)
    assert (out.ctrl_idx[:, 0] <= 3).all() and (out.ctrl_idx[:, 1:] == -1).all()
