"""Counterfactual flux interventions ([supp_mechanism_alignment]) on the real NEMSim, tiny scene."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nemsim.analysis.counterfactual import (
    INTERVENTIONS,
    analyze,
    format_table,
    intervention_controls,
    mechanism_response,
    response_batch,
    write_outputs,
)
from nemsim.inference.checkpoint import LoadedModel


@pytest.fixture(scope="module")
def setup(tiny_scene):
    from nemsim.controls import CONTROL_NAMES, lhs_design
    from nemsim.registry import build_model
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules

    rules = compile_rules(load_rules())
    torch.manual_seed(0)
    model = build_model("nemsim", tiny_scene, rules).eval()
    D = tiny_scene.field_shape[0]
    depth = torch.arange(D, dtype=torch.float32)[:, None, None]
    x0 = torch.empty(2, *tiny_scene.field_shape)
    x0[0] = ((depth - tiny_scene.resist_top) / tiny_scene.d_max_vox).clamp(-1, 1)
    x0[1] = ((depth - tiny_scene.si_top) / tiny_scene.d_max_vox).clamp(-1, 1)
    raw = lhs_design(n=3, seed=1)
    loaded = LoadedModel(model=model, name="nemsim", config={}, scene=tiny_scene, rules=rules)
    return loaded, x0, raw, CONTROL_NAMES


def test_eight_interventions_scale_only_the_two_fluxes(setup):
    _, _, raw, names = setup
    assert len(INTERVENTIONS) == 8 and (1.0, 1.0) not in INTERVENTIONS
    rows = intervention_controls(raw[0], INTERVENTIONS)
    assert rows.shape == (9, 14) and np.array_equal(rows[0], raw[0])
    ip, inn = names.index("flux_cl_plus"), names.index("flux_cl")
    others = [k for k in range(14) if k not in (ip, inn)]
    for row, (sp, sn) in zip(rows[1:], INTERVENTIONS, strict=True):
        assert row[ip] == pytest.approx(raw[0, ip] * sp) and row[inn] == pytest.approx(raw[0, inn] * sn)
        assert np.array_equal(row[others], raw[0, others])


def test_mechanism_response_per_control_vector(setup):
    loaded, x0, raw, _ = setup
    out = mechanism_response(loaded, raw[0], x0=x0)
    assert out["families"] == ["physical", "chemical", "coupled"]
    assert len(out["interventions"]) == 8
    assert all(v >= 0 for v in out["base"]["M"].values()) and out["base"]["R"] >= 0
    assert len(out["base"]["lambda"]) == loaded.rules.n_events
    np.testing.assert_allclose(np.sum(out["base"]["alpha"], axis=1), 1.0, atol=1e-5)
    iv = out["interventions"][0]
    base_m = out["base"]["M"]["coupled"]
    expect = 100 * (iv["M"]["coupled"] - base_m) / base_m
    assert iv["delta_M_pct"]["coupled"] == pytest.approx(expect, rel=1e-6)


def test_batched_equals_single(setup):
    loaded, x0, raw, _ = setup
    xb = x0[None].expand(2, *x0.shape)
    out = response_batch(loaded.model, xb, raw[:2])
    single = response_batch(loaded.model, x0[None], raw[1:2])
    np.testing.assert_allclose(out["M"][1], single["M"][0], rtol=1e-4)
    np.testing.assert_allclose(out["R"][1], single["R"][0], rtol=1e-4, atol=1e-6)


def test_analyze_table_correlations_and_outputs(setup, tmp_path):
    loaded, x0, raw, _ = setup
    cases = [(i, x0.numpy(), raw[i]) for i in range(3)]
    res = analyze(loaded.model, cases, batch_size=2)
    assert len(res["table"]) == 8 and len(res["pairs"]) == 24 and res["n_cases"] == 3
    assert set(res["correlations"]) == {"cl_plus_increase", "cl_plus_decrease", "cl_only_increase",
                                        "cl_only_decrease"}
    assert res["correlations"]["cl_plus_increase"]["n"] <= 9
    assert "Pearson" in format_table(res)
    paths = write_outputs(res, tmp_path)
    assert all(p.is_file() for p in paths.values())


def test_default_initial_state_is_the_simulators(setup):
    loaded, _, raw, _ = setup
    out = mechanism_response(loaded, raw[0])  # x0 from the scene's initial geometry
    assert len(out["interventions"]) == 8 and out["base"]["R"] is not None
