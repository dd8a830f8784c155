"""Bad input never gives a 500: 422 with a readable message, 413 for oversized bodies, 503 when busy."""

from __future__ import annotations

import json
import threading

import pytest


def _controls(default_controls, **changes):
    return {**default_controls, **changes}


BAD_BODIES = {
    "wrong type (string flux)": lambda c: {"controls": _controls(c, flux_cl="lots")},
    "wrong type (bool energy)": lambda c: {"controls": _controls(c, energy_mean_cl_plus=True)},
    "wrong type (controls list)": lambda c: {"controls": [1, 2, 3]},
    "wrong type (steps)": lambda c: {"controls": c, "steps": "ten"},
    "fractional steps": lambda c: {"controls": c, "steps": 2.5},
    "misspelt control": lambda c: {"controls": {"flux_cll": 0.01}},
    "misspelt control in a recipe": lambda c: {"recipe": [c, {"energy_mean_ar": 300.0}]},
    "unknown control": lambda c: {"controls": _controls(c, flux_xe_plus=1.0)},
    "unknown top-level field": lambda c: {"controls": c, "temperature": 300},
    "no controls": lambda c: {"steps": 3},
    "two sources": lambda c: {"controls": c, "controls_normalized": [0.0] * 14},
    "negative flux": lambda c: {"controls": _controls(c, flux_cl=-1.0)},
    "negative energy": lambda c: {"controls": _controls(c, energy_mean_ar_plus=-5.0)},
    "negative energy in recipe": lambda c: {"recipe": [c, _controls(c, energy_std_cl_plus=-1.0)]},
    "steps zero": lambda c: {"controls": c, "steps": 0},
    "steps negative": lambda c: {"controls": c, "steps": -3},
    "steps above ceiling": lambda c: {"controls": c, "steps": 101},
    "steps huge": lambda c: {"controls": c, "steps": 10**30},
    "unknown fields mode": lambda c: {"controls": c, "steps": 1, "fields": "some"},
    "unknown mesh channel": lambda c: {
        "controls": c,
        "steps": 1,
        "meshes": [{"step": 1, "channel": "resist"}],
    },
    "unknown mesh format": lambda c: {"controls": c, "steps": 1, "meshes": [{"step": 1, "format": "fbx"}]},
    "mesh step beyond": lambda c: {"controls": c, "steps": 1, "meshes": [{"step": 2}]},
    "too many meshes": lambda c: {"controls": c, "steps": 1, "meshes": [{"step": 1}] * 9},
    "normalized too short": lambda c: {"controls_normalized": [0.0] * 13},
    "normalized impossible": lambda c: {"controls_normalized": [0.0] * 8 + [-50.0] + [0.0] * 5},
    "normalized strings": lambda c: {"controls_normalized": ["0"] * 14},
    "recipe length mismatch": lambda c: {"recipe": [c, c], "steps": 3},
    "empty recipe": lambda c: {"recipe": []},
    "body is a list": lambda c: [c],
}


@pytest.mark.parametrize("name", list(BAD_BODIES))
def test_bad_body_422(client, default_controls, name):
    r = client.post("/rollout", json=BAD_BODIES[name](default_controls))
    assert r.status_code == 422, (name, r.status_code, r.text)
    body = r.json()
    assert isinstance(body["message"], str) and body["message"]
    assert all({"loc", "msg", "type"} <= set(d) for d in body["detail"])


@pytest.mark.parametrize(
    ("given", "meant"),
    [("flux_cll", "flux_cl"), ("Flux-Ar-Plus", "flux_ar_plus"), ("energy_mean_ar", "energy_mean_ar_plus")],
)
def test_unknown_control_names_the_closest(client, given, meant):
    r = client.post("/rollout", json={"controls": {given: 1.0}, "steps": 1})
    assert r.status_code == 422, r.text
    assert f"unknown control {given!r}; did you mean {meant!r}?" in r.json()["message"]
    assert r.json()["detail"][0]["loc"] == ["body", "controls"]


def test_unknown_control_far_from_any_lists_them(client):
    r = client.post("/rollout", json={"controls": {"temperature": 300.0}, "steps": 1})
    assert r.status_code == 422
    assert "unknown control 'temperature'; expected one of" in r.json()["message"]
    assert "energy_std_ar_plus" in r.json()["message"]


def test_unknown_mechanisms_parameter_names_the_closest(client):
    r = client.get("/mechanisms", params={"angel_cl": 4})
    assert r.status_code == 422 and "did you mean 'angle_cl'?" in r.json()["message"]
    r = client.get("/mechanisms", params={"factor": 2})
    assert r.status_code == 422 and "did you mean 'factors'?" in r.json()["message"]


@pytest.mark.parametrize("name", ["flux_cl", "energy_mean_ar_plus"])
def test_impossible_value_names_the_field(client, default_controls, name):
    r = client.post("/rollout", json={"controls": _controls(default_controls, **{name: -1.0})})
    assert r.status_code == 422
    assert name in r.json()["message"] and "physically impossible" in r.json()["message"]
    assert r.json()["detail"][0]["loc"] == ["body", "controls", name]


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_422(client, default_controls, literal):
    text = json.dumps({"controls": default_controls, "steps": 1}).replace(
        json.dumps(default_controls["flux_cl"]), literal, 1
    )
    assert literal in text
    r = client.post("/rollout", content=text, headers={"content-type": "application/json"})
    assert r.status_code == 422, r.text
    assert "flux_cl" in r.json()["message"]


@pytest.mark.parametrize(
    "text", ["{", "not json", "", "null", '"controls"', '{"controls": {"flux_cl": 1e5,}}']
)
def test_malformed_json_422(client, text):
    r = client.post("/rollout", content=text, headers={"content-type": "application/json"})
    assert r.status_code == 422, (text, r.status_code, r.text)


def test_wrong_content_type_422(client):
    r = client.post(
        "/rollout", content=b"controls=1", headers={"content-type": "application/x-www-form-urlencoded"}
    )
    assert r.status_code == 422


def test_configured_step_ceiling(make_client, default_controls):
    c = make_client(max_steps=3)
    assert c.post("/rollout", json={"controls": default_controls, "steps": 3}).status_code == 200
    r = c.post("/rollout", json={"controls": default_controls, "steps": 4})
    assert r.status_code == 422 and "ceiling of 3" in r.json()["message"]
    # the default (100 steps) is also held to the ceiling
    assert c.post("/rollout", json={"controls": default_controls}).status_code == 422


def test_each_app_reads_its_own_settings_without_overrides(make_client, default_controls, served):
    """The routes read the settings the app was built with; create_app sets no dependency override (with one
    set, FastAPI rebuilds every sub-dependency of a route on every request)."""
    from service.config import Settings
    from service.main import create_app

    assert create_app(Settings(warmup_steps=0), served=served).dependency_overrides == {}
    low, high = make_client(max_steps=3), make_client(max_steps=5)
    body = {"controls": default_controls, "steps": 4}
    r = low.post("/rollout", json=body)
    assert r.status_code == 422 and "ceiling of 3" in r.json()["message"]
    assert high.post("/rollout", json=body).status_code == 200


def test_longer_than_horizon_warns(make_client, default_controls, served, monkeypatch):
    monkeypatch.setattr(type(served.predictor), "horizon_steps", property(lambda self: 2))
    r = make_client().post("/rollout", json={"controls": default_controls, "steps": 3})
    assert r.status_code == 200 and any("horizon" in w for w in r.json()["warnings"])


def test_oversized_body_413(make_client, default_controls):
    c = make_client(max_body_bytes=2048)
    assert c.post("/rollout", json={"controls": default_controls, "steps": 1}).status_code == 200
    big = {"controls": default_controls, "steps": 1, "pad": "x" * 4096}
    r = c.post("/rollout", json=big)
    assert r.status_code == 413 and "2048" in r.json()["detail"]


def test_oversized_streamed_body_413(make_client, default_controls):
    """No Content-Length (chunked upload): the streamed size is counted."""
    c = make_client(max_body_bytes=2048)
    payload = json.dumps({"controls": default_controls, "steps": 1, "pad": "x" * 8192}).encode()

    def chunks():
        for i in range(0, len(payload), 512):
            yield payload[i : i + 512]

    r = c.post("/rollout", content=chunks(), headers={"content-type": "application/json"})
    assert "content-length" not in {k.lower() for k in r.request.headers}
    assert r.status_code == 413


def test_busy_503(make_client, served, default_controls, monkeypatch):
    """A full queue answers 503 with Retry-After instead of piling up work."""
    hold, release = threading.Event(), threading.Event()
    compute = type(served)._compute

    def slow(self, *args):
        hold.set()
        release.wait(10)
        return compute(self, *args)

    monkeypatch.setattr(type(served), "_compute", slow)
    c = make_client(max_queue=0)
    first = threading.Thread(
        target=c.post,
        args=("/rollout",),
        kwargs={"json": {"controls": {**default_controls, "flux_cl": 0.0137}, "steps": 1}},  # uncached
    )
    first.start()
    try:
        assert hold.wait(10)
        other = {**default_controls, "flux_cl": default_controls["flux_cl"] * 1.01}
        r = c.post("/rollout", json={"controls": other, "steps": 1})
        assert r.status_code == 503 and r.headers["retry-after"] == "1" and r.json()["message"]
    finally:
        release.set()
        first.join()


def test_absurd_magnitude_422(client, default_controls):
    r = client.post("/rollout", json={"controls": _controls(default_controls, energy_std_ar_plus=1e30)})
    assert r.status_code == 422 and "energy_std_ar_plus" in r.json()["message"]
    # a flux 50x the design maximum is a (loud) extrapolation, not an error
    r = client.post("/rollout", json={"controls": _controls(default_controls, flux_cl=1.0), "steps": 1})
    assert r.status_code == 200 and "flux_cl" in r.json()["warnings"][0]
    r = client.get("/mechanisms", params={"energy_mean_cl_plus": 1e30})
    assert r.status_code == 422 and "energy_mean_cl_plus" in r.json()["message"]
