"""Inverse design on the tiny checkpoint: spec validation, soft metrics against the exact ones, a met
spec, an unreachable one reported with its closest recipe, the search's bookkeeping."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nemsim.analysis.inverse import (
    load_inverse_context,
    rollout_to,
    search,
    spec_from_dict,
)
from nemsim.analysis.inverse.spec import edge_term, objective
from nemsim.controls import CONTROL_NAMES, INT_INDICES, from_normalized, lhs_design, to_normalized
from nemsim.geometry.profile import profile_metrics_batch
from nemsim.geometry.soft_profile import soft_profile_metrics

SMALL_SEARCH = {"screen": 6, "starts": 2, "iterations": 2, "batch": 4, "method": "adam"}


@pytest.fixture(scope="module")
def ctx(tiny_checkpoint):
    return load_inverse_context(tiny_checkpoint)


@pytest.mark.parametrize(
    "bad, match",
    [
        ({"targets": {}}, "at least one"),
        ({"targets": {"depth": 10}}, "unknown metric"),
        ({"targets": {"etch_depth": {"value": 10, "tol": 0}}}, "tol = 0 nm .* at least 0.1 nm"),
        (
            {"targets": {"etch_depth": 10}, "fixed": {"flux_cl": 1e-3}, "bounds": {"flux_cl": [1e-3, 2e-3]}},
            "both fixed and bounded",
        ),
        ({"targets": {"etch_depth": 10}, "fixed": {"angle_cl": 2.5}}, "not an integer"),
        ({"targets": {"etch_depth": 10}, "fixed": {"flux_cl": -1.0}}, "physically impossible"),
        ({"targets": {"etch_depth": 10}, "bounds": {"flux_xx": [0, 1]}}, "unknown control"),
        ({"targets": {"etch_depth": 10}, "k": 0}, "k"),
        ({"targets": {"etch_depth": 10}, "colour": "red"}, "unknown spec keys"),
    ],
)
def test_bad_specs_are_value_errors_naming_the_problem(bad, match):
    with pytest.raises(ValueError, match=match):
        spec_from_dict(bad)


def test_a_bare_number_takes_the_default_tolerance():
    spec = spec_from_dict({"targets": {"etch_depth": 80, "top_width": {"value": 45}}})
    assert spec.targets["etch_depth"].tol == 5.0 and spec.targets["top_width"].tol == 3.0


def test_soft_metrics_follow_the_exact_ones_on_simulated_states(tiny_scene):
    from nemsim.rules import compile_rules, load_rules
    from nemsim.sim import run_trajectory

    raw = lhs_design()[3].copy()
    raw[:4] *= 3.0  # etch visibly within a few steps
    states = run_trajectory(
        tiny_scene, compile_rules(load_rules()), raw, np.random.default_rng(0), n_transitions=30
    ).states[::10]  # (4, 2, D, H, W)
    exact = profile_metrics_batch(states, tiny_scene)
    soft = soft_profile_metrics(torch.from_numpy(states), tiny_scene)
    assert exact["etch_depth"][-1] > exact["etch_depth"][0]  # the states do change
    vox = tiny_scene.voxel_nm
    for name, v in soft.items():
        assert np.abs(v.numpy() - exact[name]).max() <= 0.75 * vox, name


def test_rollout_to_is_differentiable_and_matches_the_rollout(ctx):
    from nemsim.evaluation.rollout import rollout

    u = torch.zeros(2, 14, requires_grad=True)
    x = rollout_to(ctx.model, ctx.x0, u, 5)
    (g,) = torch.autograd.grad(soft_profile_metrics(x, ctx.scene)["mask_loss"].sum() + x.sum(), [u])
    assert torch.isfinite(g).all() and g.abs().sum() > 0
    with torch.no_grad():
        ref = rollout(ctx.model, ctx.x0[None].expand(2, *ctx.x0.shape).contiguous(), u.detach(), 5)[:, -1]
    assert torch.allclose(x.detach(), ref, atol=1e-5)


def test_the_search_rolls_out_through_openvino_bf16_and_torch_on_request(ctx):
    """The search's no-gradient rollouts: OpenVINO bf16 by default, within bf16 rounding of the f32 model;
    ``torch-f32`` gives ``rollout_to`` exactly; another name is refused."""
    import dataclasses

    pytest.importorskip("openvino")
    g = torch.Generator().manual_seed(3)
    u = torch.rand(3, 14, generator=g) * 2 - 1
    with torch.no_grad():
        ref = rollout_to(ctx.model, ctx.x0, u, 6)
    fast = dataclasses.replace(ctx, search_runtime="openvino")
    got = fast.final_states(u, 6)
    assert fast._search_runtime().backend == "openvino"
    assert got.shape == ref.shape and float((got - ref).abs().max()) < 0.05
    plain = dataclasses.replace(ctx, search_runtime="torch-f32")
    assert torch.equal(plain.final_states(u, 6), ref) and plain._search_runtime() is None
    with pytest.raises(ValueError, match="search_runtime"):
        dataclasses.replace(ctx, search_runtime="cuda").final_states(u, 6)


def _prediction(ctx, raw, step):
    with torch.no_grad():
        x = rollout_to(
            ctx.model, ctx.x0, torch.as_tensor(to_normalized(raw[None]), dtype=torch.float32), step
        )
    return {k: float(v[0]) for k, v in profile_metrics_batch(x.numpy(), ctx.scene).items()}


def test_a_target_the_model_predicts_is_met(ctx):
    raw = lhs_design()[7]
    raw = np.asarray(from_normalized(to_normalized(raw)))
    pred = _prediction(ctx, raw, 4)
    spec = spec_from_dict(
        {
            "targets": {
                "etch_depth": {"value": pred["etch_depth"], "tol": 0.5},
                "mask_loss": {"value": pred["mask_loss"], "tol": 0.5},
            },
            "step": 4,
            "fixed": {n: float(v) for n, v in zip(CONTROL_NAMES, raw, strict=True)},
            "k": 1,
            "search": SMALL_SEARCH,
        }
    )
    res = search(ctx, spec)
    assert res["status"] == "met", res["message"]
    top = res["recipes"][0]
    assert top["targets"]["etch_depth"]["met"] and top["targets"]["mask_loss"]["met"]
    assert top["controls"]["flux_cl"] == pytest.approx(raw[3])


def test_an_unreachable_target_is_reported_with_the_closest_recipe_and_its_miss(ctx):
    spec = spec_from_dict(
        {"targets": {"etch_depth": {"value": 10_000.0, "tol": 5}}, "step": 3, "k": 2, "search": SMALL_SEARCH}
    )
    res = search(ctx, spec, seed=1)
    assert res["status"] == "unreachable"
    assert "unreachable" in res["message"] and "etch_depth" in res["message"]
    best = res["recipes"][0]
    assert best["targets"]["etch_depth"]["miss"] > 0 and not best["targets"]["etch_depth"]["met"]
    assert len(res["recipes"]) == 2 and [r["rank"] for r in res["recipes"]] == [1, 2]


def test_search_bookkeeping_bounds_and_integer_controls(ctx):
    lo, hi = 2e-3, 4e-3
    spec = spec_from_dict(
        {
            "targets": {"top_width": 30.0},
            "step": 2,
            "k": 2,
            "bounds": {"flux_cl": [lo, hi]},
            "fixed": {"angle_cl": 7},
            "search": SMALL_SEARCH,
        }
    )
    res = search(ctx, spec)
    cost = res["cost"]
    assert cost["gradient_rollouts"] == SMALL_SEARCH["starts"] * SMALL_SEARCH["iterations"]
    assert cost["forward_rollouts"] >= SMALL_SEARCH["screen"] + SMALL_SEARCH["starts"]
    assert cost["rollouts"] == cost["forward_rollouts"] + cost["gradient_rollouts"] and cost["cpu_s"] > 0
    for r in res["recipes"]:
        assert lo * (1 - 1e-9) <= r["controls"]["flux_cl"] <= hi * (1 + 1e-9)
        assert r["controls"]["angle_cl"] == 7
        for j in INT_INDICES:
            v = r["controls"][CONTROL_NAMES[j]]
            assert v == round(v)
        assert r["training_data"]["flag"] in ("inside", "far")
        assert r["intervals"] is None  # the tiny checkpoint has no calibration file
    assert res["intervals"]["available"] is False


def test_cma_refinement_counts_its_rollouts_and_keeps_the_bounds(ctx):
    pytest.importorskip("cma")  # the optional extra nemsim[design]
    lo, hi = 2e-3, 4e-3
    spec = spec_from_dict(
        {
            "targets": {"etch_depth": 15.0},
            "step": 2,
            "k": 1,
            "bounds": {"flux_cl": [lo, hi]},
            "search": {"screen": 4, "batch": 4, "method": "cma", "cma_evals": 8},
        }
    )
    res = search(ctx, spec)
    cost = res["cost"]
    assert cost["method"] == "cma" and cost["gradient_rollouts"] == 0
    assert cost["forward_rollouts"] >= 4 + 8
    assert len(cost["objective_trace"]) >= 3  # screening + one entry per generation
    assert lo * (1 - 1e-9) <= res["recipes"][0]["controls"]["flux_cl"] <= hi * (1 + 1e-9)


def test_the_edge_term_by_hand():
    """E(u) = sum of (max(|u_j| - a, 0) / (1 - a))^2: controls at 0, 0.8, 0.9, 1 and -1 with a = 0.8 give
    0 + 0 + 0.25 + 1 + 1; its gradient pushes each control past a back toward the centre."""
    u = np.zeros(14)
    u[1:5] = 0.8, 0.9, 1.0, -1.0
    assert edge_term(u, 0.8) == pytest.approx(2.25)
    t = torch.tensor(u, dtype=torch.float64, requires_grad=True)
    edge_term(t, 0.8).backward()
    assert t.grad[:5].tolist() == pytest.approx([0.0, 0.0, 5.0, 10.0, -10.0])
    with pytest.raises(ValueError, match="edge_start"):
        spec_from_dict({"targets": {"etch_depth": 10}, "search": {"edge_start": 1.0}})


def test_the_edge_weight_steers_the_search_inward_and_leaves_the_objective_alone(ctx):
    """A target every recipe meets (15 +- 1000 nm): without the edge term (weight 0) the search ranks by J
    alone; with a heavy one its top recipe lies inside the inner box, and the reported objective is still
    J. The default weight is 0.25."""
    body = {"targets": {"etch_depth": {"value": 15.0, "tol": 1000}}, "step": 2, "k": 1}
    plain = search(ctx, spec_from_dict({**body, "search": {**SMALL_SEARCH, "edge_weight": 0.0}}), seed=3)
    plain = plain["recipes"][0]
    spec = spec_from_dict({**body, "search": {**SMALL_SEARCH, "edge_weight": 100.0}})
    inner = search(ctx, spec, seed=3)["recipes"][0]
    e_plain = edge_term(np.asarray(plain["controls_normalized"]), 0.8)
    e_inner = edge_term(np.asarray(inner["controls_normalized"]), 0.8)
    assert e_inner < 0.05 and e_inner <= e_plain and e_plain > 0.5
    assert spec_from_dict(body).search.edge_weight == 0.25
    assert inner["objective"] == pytest.approx(objective(inner["predicted"], spec), abs=1e-4)


def test_a_trench_model_searches_on_its_trench(tiny_section_checkpoint):
    """A cross-section checkpoint's inverse context is its trench (kind, x0 constant along the line), and a
    search on it answers with recipes."""
    ctx = load_inverse_context(tiny_section_checkpoint)
    assert ctx.scene.kind == "trench"
    assert torch.equal(ctx.x0, ctx.x0[..., :1, :].expand_as(ctx.x0))
    spec = spec_from_dict({"targets": {"etch_depth": 20.0}, "step": 4, "k": 1, "search": SMALL_SEARCH})
    res = search(ctx, spec)
    assert res["recipes"] and np.isfinite(res["recipes"][0]["predicted"]["etch_depth"])
