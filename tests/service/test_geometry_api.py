"""The `geometry` block of the API: validated (kind, positive finite numbers, the fit to the
grid: 422 with one line), echoed as built, part of the rollout cache key, listed by GET /model with the
trained ranges; a kind the model was not trained on is refused naming the kinds it knows; a feature outside
the trained ranges is answered but never trusted."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

HOLE_60 = {"kind": "hole", "cd_nm": 60.0, "mask_nm": 80.0}


def _message(r) -> str:
    body = r.json()
    return str(body.get("message", "")) + " " + str(body.get("detail", ""))


def test_model_lists_the_default_feature_and_the_trained_ranges(client):
    geo = client.get("/model").json()["geometry"]
    assert geo["default"] == {"kind": "hole", "cd_nm": 40.0, "mask_nm": 80.0}
    assert geo["kinds"] == {"hole": {"cd_nm": [40.0, 40.0], "mask_nm": [80.0, 80.0]}}
    assert "scene" in geo["source"]


@pytest.mark.parametrize(
    "geometry",
    [
        {"kind": "slot", "cd_nm": 40, "mask_nm": 80},
        {"kind": "hole", "cd_nm": -1, "mask_nm": 80},
        {"kind": "hole", "cd_nm": 0, "mask_nm": 80},
        {"kind": "hole", "cd_nm": "40", "mask_nm": 80},
        {"kind": "hole", "cd_nm": 40, "mask_nm": 1e300},
        {"kind": "hole", "cd_nm": 40},
        {"kind": "hole", "cd_nm": 40, "mask_nm": 80, "pitch_nm": 100},
        "hole",
    ],
)
def test_a_malformed_block_is_422(client, default_controls, geometry):
    r = client.post("/rollout", json={"controls": default_controls, "steps": 1, "geometry": geometry})
    assert r.status_code == 422, r.text
    assert "geometry" in r.text


def test_a_feature_that_does_not_fit_the_grid_is_422_with_the_range(client, default_controls):
    r = client.post("/rollout", json={"controls": default_controls, "steps": 1,
                                      "geometry": {"kind": "hole", "cd_nm": 100, "mask_nm": 80}})  # fmt: skip
    assert r.status_code == 422
    assert "does not fit scene 'tiny'" in _message(r) and "16..88 nm" in _message(r)
    assert "\n" not in r.json()["message"]


def test_a_trench_on_the_hole_model_is_refused_naming_the_kinds(client, default_controls):
    trench = {"kind": "trench", "cd_nm": 40, "mask_nm": 80}
    for path, body in [
        ("/rollout", {"controls": default_controls, "steps": 1}),
        ("/simulations", {"controls": default_controls, "steps": 1}),
        ("/design", {"targets": {"etch_depth": 50}}),
        ("/mechanisms", {"controls": {}}),
    ]:
        r = client.post(path, json={**body, "geometry": trench})
        assert r.status_code == 422, (path, r.text)
        assert "trained on hole features only" in _message(r) and "['hole']" in _message(r), path


def test_the_default_is_echoed_and_trusted_as_before(client, default_controls):
    body = client.post("/rollout", json={"controls": default_controls, "steps": 2}).json()
    assert body["geometry"] == {"kind": "hole", "cd_nm": 40.0, "mask_nm": 80.0}
    assert body["trust"]["geometry"]["inside"] is True
    assert "controls_level" not in body["trust"]
    thicker = {"kind": "hole", "cd_nm": 40, "mask_nm": 82}
    same = client.post("/rollout", json={"controls": default_controls, "steps": 2, "geometry": thicker})
    same = same.json()
    assert same["id"] == body["id"] and same["cached"]  # 82 nm of mask is built as 80 on 8 nm voxels
    assert same["geometry"]["mask_nm"] == 80.0


def test_a_60nm_hole_on_the_40nm_model_is_never_trusted(client, default_controls):
    """The issue's target: outside the trained geometry the verdict is reject, whatever the controls."""
    base = client.post("/rollout", json={"controls": default_controls, "steps": 2}).json()
    r = client.post("/rollout", json={"controls": default_controls, "steps": 2, "geometry": HOLE_60})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["geometry"] == HOLE_60
    trust = body["trust"]
    assert trust["level"] == "reject" and trust["level"] != "ok"
    assert trust["geometry"] == {
        "feature": HOLE_60, "inside": False,
        "trained": {"hole": {"cd_nm": [40.0, 40.0], "mask_nm": [80.0, 80.0]}},
    }  # fmt: skip
    assert "cd 60 nm" in trust["reason"] and "hole, cd 40 nm, mask 80 nm" in trust["reason"]
    assert trust["controls_level"] == base["trust"]["level"]
    assert any("outside the features this model was trained on" in w for w in body["warnings"])
    # the cache key holds the geometry: another id, another rollout; a repeat is a hit on the same id
    assert body["id"] != base["id"] and body["metrics"] != base["metrics"]
    again = client.post("/rollout", json={"controls": default_controls, "steps": 2, "geometry": HOLE_60})
    assert again.json()["id"] == body["id"] and again.json()["cached"]


def test_the_cache_key_includes_the_geometry(served, default_controls):
    predictor = served.predictor
    from nemsim.geometry.feature import Feature

    schedule = predictor.schedule(default_controls, 2)
    default_id = served.rollout_id(schedule)
    assert served.rollout_id(schedule, predictor.case(None)) == default_id
    assert served.rollout_id(schedule, predictor.case(Feature("hole", 60.0, 80.0))) != default_id
    assert served.rollout_id(schedule, predictor.case(Feature("hole", 60.0, 72.0))) != served.rollout_id(
        schedule, predictor.case(Feature("hole", 60.0, 80.0))
    )


def test_exports_of_a_feature_read_its_scene(client, default_controls):
    body = {"controls": default_controls, "steps": 1, "geometry": HOLE_60}
    rid = client.post("/rollout", json=body).json()["id"]
    text = client.get(f"/rollouts/{rid}/metrics.csv").text
    assert '# geometry: {"kind": "hole", "cd_nm": 60.0, "mask_nm": 80.0}' in text
    assert client.get(f"/rollouts/{rid}/mesh?step=0&format=ply").status_code == 200


def test_trust_inside_a_recorded_range(tmp_path, tiny_scene, rules, default_controls):
    """A checkpoint recording a cd range trusts a 60 nm hole inside it as far as the geometry goes."""
    from nemsim.controls import to_normalized
    from nemsim.geometry.feature import Feature
    from nemsim.inference.checkpoint import save_checkpoint
    from nemsim.registry import build_model, model_config
    from service.inverse import rollout_trust
    from service.served_model import ServedModel

    model = build_model("nemsim", tiny_scene, rules)
    path = save_checkpoint(
        tmp_path / "ranged.pt", model, model_name="nemsim",
        model_config=dataclasses.asdict(model_config("nemsim", tiny_scene)), scene=tiny_scene, rules=rules,
        geometry={"hole": {"cd_nm": [32.0, 64.0], "mask_nm": [80.0, 80.0]}},
    )  # fmt: skip
    served = ServedModel.from_checkpoint(path, runtime_backend="torch")
    raw = np.array(list(default_controls.values()))[None]
    inside = rollout_trust(served, raw, to_normalized(raw), Feature("hole", 60.0, 80.0), benchmarks=tmp_path)
    assert inside["geometry"]["inside"] is True and "controls_level" not in inside
    outside = rollout_trust(served, raw, to_normalized(raw), Feature("hole", 72.0, 80.0), benchmarks=tmp_path)
    assert outside["level"] == "reject" and "cd 32..64 nm" in outside["reason"]


def test_jobs_and_mechanisms_take_and_echo_the_geometry(client, default_controls):
    body = {"controls": {"flux_cl": 0.01}, "factors": [0.5], "geometry": HOLE_60}
    r = client.post("/mechanisms", json=body)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["geometry"] == HOLE_60 and body["controls"]["flux_cl"] == 0.01
    assert any("outside the features" in w for w in body["warnings"])
    default = client.post("/mechanisms", json={"factors": [0.5]}).json()
    assert default["geometry"]["cd_nm"] == 40.0 and default["result"] != body["result"]
    created = client.post("/design", json={"targets": {"etch_depth": 50}, "geometry": HOLE_60})
    assert created.status_code == 202 and created.json()["geometry"] == HOLE_60
    client.delete(created.json()["location"])
    sim = {"controls": default_controls, "steps": 1, "geometry": HOLE_60}
    created = client.post("/simulations", json=sim)
    assert created.status_code == 202 and created.json()["geometry"] == HOLE_60
    client.delete(created.json()["location"])


def test_the_openapi_schema_documents_the_block(client):
    schema = client.get("/openapi.json").json()
    geo = schema["components"]["schemas"]["Geometry"]
    assert geo["properties"]["kind"]["enum"] == ["hole", "trench"]
    assert geo["properties"]["cd_nm"]["exclusiveMinimum"] == 0
    assert "post" in schema["paths"]["/mechanisms"] and "get" in schema["paths"]["/mechanisms"]
