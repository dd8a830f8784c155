"""Validation gaps found under fuzzing (defects 1-5, 7): each request here was once accepted or answered
in another shape."""

from __future__ import annotations

import pytest


def _controls(default_controls, **changes):
    return {**default_controls, **changes}


# --- defect 1: every finite flux passed the scale guard ----------------------------------------------


@pytest.mark.parametrize("value", [1e300, 1e30, 1e6])
def test_absurd_flux_422(client, default_controls, value):
    r = client.post("/rollout", json={"controls": _controls(default_controls, flux_cl=value), "steps": 1})
    assert r.status_code == 422, r.text
    assert "flux_cl" in r.json()["message"] and "far outside" in r.json()["message"]
    r = client.get("/mechanisms", params={"flux_cl": value})
    assert r.status_code == 422 and "flux_cl" in r.json()["message"]


def test_large_but_meaningful_flux_is_an_extrapolation(client, default_controls):
    """50x the design maximum is still a process: answered, with a warning naming the control."""
    r = client.post("/rollout", json={"controls": _controls(default_controls, flux_cl=1.0), "steps": 1})
    assert r.status_code == 200 and any("flux_cl" in w for w in r.json()["warnings"])


def test_guard_is_in_the_schema(client):
    from service.schemas import guard_max

    props = client.get("/openapi.json").json()["components"]["schemas"]["Controls"]["properties"]
    assert props["flux_cl"]["maximum"] == pytest.approx(guard_max("flux_cl"))
    assert props["energy_mean_cl_plus"]["maximum"] == pytest.approx(guard_max("energy_mean_cl_plus"))


# --- defect 2: integer controls accepted fractions ---------------------------------------------------


def test_fractional_integer_control_422(client, default_controls):
    r = client.post("/rollout", json={"controls": _controls(default_controls, angle_cl=2.5), "steps": 1})
    assert r.status_code == 422 and "angle_cl" in r.json()["message"] and "integer" in r.json()["message"]
    assert client.get("/mechanisms", params={"angle_cl": 2.5}).status_code == 422
    ok = client.post("/rollout", json={"controls": _controls(default_controls, angle_cl=2.0), "steps": 1})
    assert ok.status_code == 200 and ok.json()["controls"]["angle_cl"] == 2.0


def test_integer_controls_in_the_schema(client):
    props = client.get("/openapi.json").json()["components"]["schemas"]["Controls"]["properties"]
    assert props["angle_cl"]["multipleOf"] == 1 and "multipleOf" not in props["flux_cl"]


# --- defect 3: steps was loosely typed ---------------------------------------------------------------


@pytest.mark.parametrize("steps", ["1", "100", True, False, 1.5])
def test_steps_must_be_a_json_integer(client, default_controls, steps):
    r = client.post("/rollout", json={"controls": default_controls, "steps": steps})
    assert r.status_code == 422, (steps, r.text)
    assert "steps" in r.json()["message"]


def test_integral_number_is_a_json_integer(client, default_controls):
    """JSON Schema counts 1.0 as an integer, so the server does too."""
    r = client.post("/rollout", json={"controls": default_controls, "steps": 1.0, "meshes": [{"step": 1.0}]})
    assert r.status_code == 200 and r.json()["steps"] == 1


@pytest.mark.parametrize("step", ["1", True])
def test_mesh_step_must_be_a_json_integer(client, default_controls, step):
    r = client.post("/rollout", json={"controls": default_controls, "steps": 1, "meshes": [{"step": step}]})
    assert r.status_code == 422, r.text


# --- defect 4: repeated query parameters and the factors list ----------------------------------------


def test_repeated_control_in_query_422(client):
    r = client.get("/mechanisms?angle_cl=2&angle_cl=3")
    assert r.status_code == 422, r.text
    assert "angle_cl" in r.json()["message"] and "more than once" in r.json()["message"]


def test_factors_comma_and_repeated_forms_agree(client):
    a = client.get("/mechanisms?factors=0.5,2")
    b = client.get("/mechanisms?factors=0.5&factors=2")
    assert a.status_code == 200, a.text
    assert a.json()["result"] == b.json()["result"]
    pairs = {(i["s_cl_plus"], i["s_cl"]) for i in a.json()["result"]["interventions"]}
    assert (2.0, 0.5) in pairs and len(pairs) == 8


def test_unknown_query_parameter_422(client):
    r = client.get("/mechanisms", params={"flux_xe": 1})
    assert r.status_code == 422 and "flux_xe" in r.json()["message"]


# --- defect 5: one error body shape ------------------------------------------------------------------


def _uniform(r, status):
    assert r.status_code == status, (r.status_code, r.text)
    body = r.json()
    assert set(body) >= {"detail", "message"}, body
    assert isinstance(body["message"], str) and body["message"] and "\n" not in body["message"]
    return body


def test_truncated_json_message(client):
    body = _uniform(
        client.post(
            "/rollout", content=b'{"steps": 1, "controls": {', headers={"content-type": "application/json"}
        ),
        422,
    )
    assert "JSON" in body["message"] and not body["message"][0].isdigit()


def test_invalid_utf8_400(client):
    body = _uniform(
        client.post(
            "/rollout", content=b'{"steps": "\xff\xfe"}', headers={"content-type": "application/json"}
        ),
        400,
    )
    assert "UTF-8" in body["message"] or "JSON" in body["message"]


def test_unknown_route_404_and_wrong_method_405(client):
    _uniform(client.get("/nope"), 404)
    _uniform(client.get("/rollout"), 405)
    _uniform(client.get("/rollouts/" + "a" * 24 + "/mesh"), 404)


def test_unhandled_error_500_is_generic(served, monkeypatch, default_controls):
    from fastapi.testclient import TestClient

    from service.config import Settings
    from service.main import create_app

    def boom(*args, **kwargs):
        raise RuntimeError("secret internals /home/someone/x.pt")

    monkeypatch.setattr(type(served), "_compute", boom)
    app = create_app(Settings(warmup_steps=0), served=served)
    with TestClient(app, raise_server_exceptions=False) as c:
        controls = _controls(default_controls, flux_cl=0.0123)
        body = _uniform(c.post("/rollout", json={"controls": controls, "steps": 1}), 500)
    assert "secret" not in str(body) and "/home" not in str(body)


# --- defect 7: the schema states what the server enforces --------------------------------------------


def test_schema_states_the_rules(make_client):
    default = make_client().get("/openapi.json").json()["components"]["schemas"]["RolloutRequest"]
    assert {tuple(b["required"]) for b in default["oneOf"]} == {
        ("controls",),
        ("controls_normalized",),
        ("recipe",),
    }
    doc = make_client(max_steps=7, max_meshes=3).get("/openapi.json").json()
    req = doc["components"]["schemas"]["RolloutRequest"]
    # below the default of 100 steps, `steps` must be given unless a recipe sets it
    assert {tuple(b["required"]) for b in req["oneOf"]} == {
        ("controls",),
        ("controls_normalized",),
        ("recipe",),
    }
    assert {tuple(b["required"]) for b in req["anyOf"]} == {("recipe",), ("steps",)}
    assert "anyOf" not in default
    steps = next(b for b in req["properties"]["steps"]["anyOf"] if b.get("type") == "integer")
    assert steps["maximum"] == 7 and steps["minimum"] == 1 and req["properties"]["meshes"]["maxItems"] == 3
    rollout = doc["paths"]["/rollout"]["post"]["responses"]
    for code in ("400", "413", "422", "503"):
        assert rollout[code]["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody"), code


def _cross_field_cases(default_controls):
    """(label, body): requests on either side of the two cross-field rules (recipe length = steps; an
    inline mesh's step <= the rollout's steps, default 100)."""
    row = dict(default_controls)
    mesh = {"channel": "si", "format": "stl"}
    return [
        ("recipe of 3, steps 3", {"recipe": [row] * 3, "steps": 3}),
        ("recipe of 3, no steps", {"recipe": [row] * 3}),
        ("recipe of 3, steps null", {"recipe": [row] * 3, "steps": None}),
        ("recipe of 3, steps 2", {"recipe": [row] * 3, "steps": 2}),
        ("recipe of 2, steps 3", {"recipe": [row] * 2, "steps": 3}),
        ("mesh at the last step", {"controls": row, "steps": 2, "meshes": [{"step": 2, **mesh}]}),
        ("mesh past the last step", {"controls": row, "steps": 2, "meshes": [{"step": 3, **mesh}]}),
        ("mesh past a recipe", {"recipe": [row] * 2, "meshes": [{"step": 3, **mesh}]}),
        ("mesh at a recipe's end", {"recipe": [row] * 2, "meshes": [{"step": 2, **mesh}]}),
        ("default steps, mesh 100", {"controls": row, "meshes": [{"step": 100, **mesh}]}),
        ("default steps, mesh 101", {"controls": row, "meshes": [{"step": 101, **mesh}]}),
    ]


def test_cross_field_rules_are_described_and_enforced(make_client, default_controls):
    """A request the server accepts is valid under the published schema (it is never stricter); the two
    cross-field rules, which the plain schema leaves to the field descriptions, are refused with 422."""
    import jsonschema_rs

    c = make_client(max_steps=120)
    doc = c.get("/openapi.json").json()
    request = doc["components"]["schemas"]["RolloutRequest"]
    assert "allOf" not in request
    assert "must be its length" in request["properties"]["recipe"]["description"]
    assert "at most the rollout's steps" in request["properties"]["meshes"]["description"]
    validator = jsonschema_rs.Draft202012Validator(
        {"$ref": "#/components/schemas/RolloutRequest", "components": doc["components"]}
    )
    refused = []
    for label, body in _cross_field_cases(default_controls):
        r = c.post("/rollout", json=body)
        assert r.status_code in (200, 422) and validator.is_valid(body), (label, r.status_code)
        if r.status_code == 422:
            refused.append(label)
            assert any(word in r.json()["message"] for word in ("steps", "meshes")), r.json()
    assert refused == [
        "recipe of 3, steps 2",
        "recipe of 2, steps 3",
        "mesh past the last step",
        "mesh past a recipe",
        "default steps, mesh 101",
    ]


def test_normalized_bounds_in_schema_match_the_server(client):
    from service.schemas import NORM_MAX, NORM_MIN

    doc = client.get("/openapi.json").json()
    arr = next(
        b
        for b in doc["components"]["schemas"]["RolloutRequest"]["properties"]["controls_normalized"]["anyOf"]
        if b.get("type") == "array"
    )
    assert [p["maximum"] for p in arr["prefixItems"]] == list(NORM_MAX)
    edge = [float(v) for v in NORM_MAX]
    assert client.post("/rollout", json={"controls_normalized": edge, "steps": 1}).status_code == 200
    beyond = [*edge[:3], edge[3] * (1 + 1e-9), *edge[4:]]
    r = client.post("/rollout", json={"controls_normalized": beyond, "steps": 1})
    assert r.status_code == 422 and "flux_cl" in r.json()["message"]
    low = [float(v) for v in NORM_MIN]  # every control at its physical minimum (0)
    assert client.post("/rollout", json={"controls_normalized": low, "steps": 1}).status_code == 200


@pytest.mark.parametrize("body", [{"controls": None, "controls_normalized": [0.0] * 14, "steps": 1}])
def test_null_source_counts_as_absent(client, body):
    assert client.post("/rollout", json=body).status_code == 200
