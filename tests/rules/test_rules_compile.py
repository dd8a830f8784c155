"""Compiled tensors of rules/cl_si.yaml against hand-written rows ([supp_rule_schema], [supp_eic],
[supp_mechanism_mapping])."""

from __future__ import annotations

import math

import numpy as np

from nemsim.rules import compile_rules, parse_rules
from nemsim.rules.compile import META_FLAGS
from nemsim.rules.schema import canonical_text


def N(v: float) -> float:  # energy normalization with the 160-500 eV bounds of the control table
    return 2 * (v - 160) / 340 - 1


def meta(*on: str) -> list[float]:
    return [1.0 if f in on else 0.0 for f in META_FLAGS]


SiCl, SiCl2 = 5, 6  # species columns


def test_shapes(tensors):
    E = 37
    assert tensors.R.shape == (E, 22) and tensors.phi.shape == (E, 35) and tensors.psi.shape == (E, 7)
    assert tensors.alpha0.shape == (E, 3) and tensors.r_mech.shape == (E, 3)
    assert tensors.w_src.shape == (E, 8) and tensors.w_sink.shape == (E, 8) and tensors.s_dep.shape == (E,)
    assert tensors.ctrl_idx.shape == (E, 4) and tensors.prob_params.shape == (E, 5)
    assert tensors.yield_params.shape == (E, 4)
    assert tensors.is_primary.sum() == 22
    np.testing.assert_allclose(tensors.alpha0.sum(1), 1.0)
    assert set(np.unique(tensors.r_mech)) <= {0.0, 1.0}
    assert len(tensors.sha256) == 64


def test_row_E1(tensors):
    e = 0
    np.testing.assert_allclose(
        tensors.R[e], [1, 0, 0, 0, 3, 4, -1, -1, 0, 0.55, 0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, -1, 0]
    )
    r_bar = [0.5, 0, 0, 0, 0.5, 0.55, 0, 0, 0, 0, 0, 0.5, 1.0, 0, 0, 0, 0, 0]
    np.testing.assert_allclose(tensors.phi[e], r_bar + meta("neutral", "react", "src"))
    np.testing.assert_allclose(tensors.psi[e], [2 / 3, 0, 0, 0, 0.5, 0.5, 0])
    np.testing.assert_allclose(tensors.alpha0[e], [0.05, 0.90, 0.05])
    np.testing.assert_array_equal(tensors.r_mech[e], [0, 1, 1])
    expect_src = np.zeros(8)
    expect_src[SiCl] = 1.0
    np.testing.assert_array_equal(tensors.w_src[e], expect_src)
    assert not tensors.src_is_yield[e].any() and tensors.w_sink[e].sum() == 0 and tensors.s_dep[e] == 0
    assert tensors.prob_model[e] == 0 and tensors.yield_model[e] == 0 and tensors.angle_kind[e] == 0


def test_row_E8(tensors):
    e = 7
    assert tensors.names[e] == "Clp_on_SiCl_phys"
    np.testing.assert_allclose(
        tensors.R[e], [2, 2, 1, 0, 1, 5, 8, 9, 1, 35, 100, 0.10, 0.5, 1, 1, 0, 35, 60, 2.8, 1.5, -1, 0]
    )
    r_bar = [1, 2 / 7, 1 / 4, 0, 1, 0, N(35), N(100), 0.10, 0.5, 0.5, 1, 0, N(35), 0.5, math.log(2.8 / 1.5),
             0, 0]  # fmt: skip
    flags = meta("ion", "angle_P", "energy", "yamamura", "sputter", "src", "target_chlor", "group_both")
    np.testing.assert_allclose(tensors.phi[e], r_bar + flags, atol=1e-12)
    np.testing.assert_allclose(tensors.psi[e], [1, 2 / 7, 1 / 4, 0, 1, 1, 0.5])
    np.testing.assert_allclose(tensors.alpha0[e], [0.05, 0.05, 0.90])
    np.testing.assert_array_equal(tensors.r_mech[e], [1, 0, 1])
    assert tensors.w_src[e, SiCl2] == 1.0 and tensors.src_is_yield[e, SiCl2]
    assert tensors.src_is_yield[e].sum() == 1
    np.testing.assert_allclose(tensors.prob_params_norm[e], [N(35), N(100), 0.10, 0.5, 1])
    np.testing.assert_allclose(tensors.yield_params_norm[e], [N(35), 60, 2.8, 1.5])


def test_row_E9(tensors):
    e = 8
    assert tensors.names[e] == "Clp_on_SiCl_chem"
    np.testing.assert_allclose(
        tensors.R[e], [2, 2, 1, 0, 1, 5, 8, 9, 1, 10, 100, 0.20, 0.5, 2, 0, 1.0, 0, 0, 0, 0, -1, 0]
    )
    r_bar = [1, 2 / 7, 1 / 4, 0, 1, 0, N(10), N(100), 0.20, 0.5, 1.0, 0.5, 1.0, 0, 0, 0, 0, 0]
    flags = meta("ion", "angle_C", "energy", "etch", "src", "target_chlor", "group_both")
    np.testing.assert_allclose(tensors.phi[e], r_bar + flags, atol=1e-12)
    np.testing.assert_allclose(tensors.psi[e], [1, 2 / 7, 1 / 4, 0, 1, 0.5, 1])
    np.testing.assert_array_equal(tensors.r_mech[e], [0, 1, 1])
    assert tensors.w_src[e, SiCl2] == 1.0 and not tensors.src_is_yield[e].any()


def test_row_E12(tensors):
    e = 11
    assert tensors.names[e] == "Clp_on_Resist_phys"
    np.testing.assert_allclose(
        tensors.R[e], [0, 2, 4, 0, 1, 5, 8, 9, 1, 15, 150, 0.01, 0.5, 1, 1, 0, 15, 60, 1.2, 1.0, -1, 0]
    )
    r_bar = [0, 2 / 7, 1, 0, 1, 0, N(15), N(150), 0.01, 0.5, 0.5, 1, 0, N(15), 0.5, math.log(1.2), 0, 0]
    flags = meta("ion", "angle_P", "energy", "yamamura", "sputter", "src", "target_resist", "group_physical")
    np.testing.assert_allclose(tensors.phi[e], r_bar + flags, atol=1e-12)
    np.testing.assert_allclose(tensors.psi[e], [1 / 3, 2 / 7, 1, 0, 1, 1, 0.5])
    np.testing.assert_allclose(tensors.alpha0[e], [0.90, 0.05, 0.05])
    np.testing.assert_array_equal(tensors.r_mech[e], [1, 0, 1])
    assert tensors.w_src[e, SiCl] == 1.0 and tensors.src_is_yield[e, SiCl]


def test_row_E23(tensors):
    e = 22
    assert tensors.names[e] == "SiCl_dep_on_Si"
    np.testing.assert_allclose(
        tensors.R[e], [1, 5, 0, 1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, -1, 0, 0, 0, 0, 0, 5, 0.02]
    )
    r_bar = [0.5, 5 / 7, 0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 6 / 8, 0.02]
    np.testing.assert_allclose(tensors.phi[e], r_bar + meta("dep", "deposit", "sink"))
    np.testing.assert_allclose(tensors.psi[e], [2 / 3, 5 / 7, 0, 1, 0, 0, 0])
    np.testing.assert_allclose(tensors.alpha0[e], [0.05, 0.90, 0.05])
    np.testing.assert_array_equal(tensors.r_mech[e], [0, 1, 1])
    expect_sink = np.zeros(8)
    expect_sink[SiCl] = 1.0
    np.testing.assert_array_equal(tensors.w_sink[e], expect_sink)
    assert tensors.w_src[e].sum() == 0 and tensors.s_dep[e] == 0.02
    np.testing.assert_array_equal(tensors.ctrl_idx[e], [-1, -1, -1, -1])


def test_catalog_structure(tensors):
    # ion events bind their projectile's flux / angle / energy mean / energy std
    np.testing.assert_array_equal(tensors.ctrl_idx[17], [0, 7, 12, 13])  # E18 Ar+ on Si
    np.testing.assert_array_equal(tensors.ctrl_idx[12], [2, 6, 10, 11])  # E13 Cl2+ on Si
    assert (tensors.prob_params[6:22, 3] == 0.5).all()  # n_e = 0.5 for every ion event
    assert (tensors.s_dep[22:] == 0.02).all() and tensors.w_sink[22:].sum() == 15
    # every deposition event is chemical with chemical + coupled roles
    assert (tensors.group[22:] == 1).all() and (tensors.r_mech[22:] == [0, 1, 1]).all()


def test_sha_and_canonical_round_trip(spec, tensors):
    again = compile_rules(parse_rules(tensors.source_text))
    assert again.sha256 == tensors.sha256
    assert canonical_text(parse_rules(canonical_text(spec))) == tensors.source_text
    np.testing.assert_array_equal(again.R, tensors.R)


def test_sha_changes_with_content(spec, rules_text):
    other = compile_rules(parse_rules(rules_text.replace("p_const: 0.55", "p_const: 0.56")))
    assert other.sha256 != compile_rules(spec).sha256


def test_torch_buffers(tensors):
    import torch

    bufs = tensors.torch_buffers()
    assert bufs["R"].dtype == torch.float32 and bufs["ctrl_idx"].dtype == torch.int64
    assert bufs["is_primary"].dtype == torch.bool and bufs["phi"].shape == (37, 35)
