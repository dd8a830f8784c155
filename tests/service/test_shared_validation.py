"""One validation layer for `/rollout`, `/simulations` and `/design`: the same controls are refused everywhere
(422 naming the control, the value and the accepted range), targets and tolerances outside their physical
ranges are 422, and the `intervals` flag takes JSON booleans only."""

from __future__ import annotations

import pytest

BAD_CONTROLS = [
    ("flux_cl", 1e308, "far outside"),
    ("flux_cl", 25.0, "far outside"),  # past the guard of 20 (10^3 x the design maximum)
    ("energy_mean_ar_plus", -1.0, "physically impossible"),
    ("angle_cl", 2.5, "not an integer"),
]


@pytest.mark.parametrize("name, value, word", BAD_CONTROLS)
def test_rollout_simulations_and_design_refuse_the_same_controls(client, default_controls, name, value, word):
    controls = {**default_controls, name: value}
    for path, body in (
        ("/rollout", {"controls": controls, "steps": 1}),
        ("/simulations", {"controls": controls, "steps": 1}),
        ("/design", {"targets": {"etch_depth": 20}, "fixed": {name: value}}),
    ):
        r = client.post(path, json=body)
        assert r.status_code == 422, (path, r.text)
        message = r.json()["message"]
        assert f"{name} = {value:g}" in message and word in message, (path, message)
    assert "fixed." + name in message  # /design names the field


def test_design_refuses_out_of_range_bounds(client):
    r = client.post("/design", json={"targets": {"etch_depth": 20}, "bounds": {"flux_cl": [0.001, 1e308]}})
    assert r.status_code == 422 and "bounds.flux_cl[1]" in r.json()["message"], r.text


@pytest.mark.parametrize(
    "target, words",
    [
        (1e308, ["targets.etch_depth", "1e+308", "0..160 nm"]),  # the tiny scene's Si is 160 nm thick
        (-1e308, ["targets.etch_depth", "-1e+308", ">= 0"]),
        (161.0, ["targets.etch_depth", "Si thickness"]),
        ({"value": 20, "tol": 1e-300}, ["targets.etch_depth.tol", "1e-300", "at least 0.1 nm"]),
        ({"value": 20, "tol": 0}, ["targets.etch_depth.tol", "at least 0.1 nm"]),
        ({"value": 20, "tol": 1e308}, ["targets.etch_depth.tol", "at most 160 nm"]),
        ({"value": 1e308, "tol": 5}, ["targets.etch_depth.value", "1e+308"]),
    ],
)
def test_design_refuses_targets_and_tolerances_outside_their_ranges(client, target, words):
    r = client.post("/design", json={"targets": {"etch_depth": target}})
    assert r.status_code == 422, r.text
    message = r.json()["message"]
    assert all(w in message for w in words), message


def test_edge_values_are_still_accepted(default_controls):
    """The limits themselves are valid input: the guard of flux_cl, the Si thickness, the finest tolerance."""
    from nemsim.analysis.inverse import check_targets, spec_from_dict
    from nemsim.scenes import TINY
    from service.inverse_schemas import DesignRequest
    from service.schemas import SimulationRequest

    body = DesignRequest.model_validate(
        {"targets": {"etch_depth": {"value": 160, "tol": 0.1}, "mask_loss": 0}, "fixed": {"flux_cl": 20}}
    )
    check_targets(spec_from_dict(body.spec_dict()).targets, TINY)
    SimulationRequest.model_validate({"controls": {**default_controls, "flux_cl": 20.0}, "steps": 1})


def test_rollout_at_the_guard_is_answered(client, default_controls):
    r = client.post("/rollout", json={"controls": {**default_controls, "flux_cl": 20.0}, "steps": 1})
    assert r.status_code == 200 and any("flux_cl" in w for w in r.json()["warnings"]), r.text


@pytest.mark.parametrize("flag", ["yes", "off", "true", 0, 1, None])
def test_intervals_takes_json_booleans_only(client, default_controls, flag):
    r = client.post("/rollout", json={"controls": default_controls, "steps": 1, "intervals": flag})
    assert r.status_code == 422, r.text
    assert "intervals" in r.json()["message"]


def test_intervals_true_and_false_are_accepted(client, default_controls):
    for flag in (True, False):
        r = client.post("/rollout", json={"controls": default_controls, "steps": 1, "intervals": flag})
        assert r.status_code == 200, r.text

