"""POST /rollout and GET /rollouts/{id}/mesh: results, caching, fields, recipes, meshes."""

from __future__ import annotations

import base64
import threading

import numpy as np
import pytest


def test_rollout_metrics(client, default_controls):
    r = client.post("/rollout", json={"controls": default_controls, "steps": 3})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["steps"] == 3 and body["metric_units"] == "nm" and body["warnings"] == []
    assert body["times_s"] == pytest.approx([0.0, 0.1, 0.2, 0.3])
    assert set(body["metrics"]) >= {
        "etch_depth",
        "top_width",
        "neck_width",
        "bottom_width",
        "bowing",
        "mask_loss",
    }
    assert all(len(v) == 4 for v in body["metrics"].values())
    assert body["metrics"]["etch_depth"][0] == pytest.approx(
        0.0, abs=1e-6
    )  # the initial geometry is unetched
    assert body["controls"] == pytest.approx(default_controls) and body["recipe"] is None
    assert body["fields"] is None and body["meshes"] == []
    assert body["timings"]["total_ms"] > 0


def test_repeat_is_cached(client, default_controls):
    req = {"controls": default_controls, "steps": 4}
    first = client.post("/rollout", json=req).json()
    second = client.post("/rollout", json=req).json()
    assert second["id"] == first["id"] and second["cached"] is True
    assert second["timings"]["rollout_ms"] == 0.0
    assert second["metrics"] == first["metrics"]
    other = client.post("/rollout", json={**req, "steps": 5}).json()
    assert other["id"] != first["id"]


def test_cache_hit_recomputes_nothing(client, default_controls, monkeypatch):
    """A repeat must not call the model at all."""
    import nemsim.evaluation.rollout as lib

    req = {"controls": default_controls, "steps": 2}
    assert client.post("/rollout", json=req).status_code == 200

    def boom(*a, **k):
        raise AssertionError("rollout recomputed")

    monkeypatch.setattr(lib, "rollout", boom)
    assert client.post("/rollout", json=req).json()["cached"] is True


def test_controls_normalized(client):
    r = client.post("/rollout", json={"controls_normalized": [0.0] * 14, "steps": 2})
    assert r.status_code == 200 and r.json()["warnings"] == []
    r = client.post("/rollout", json={"controls_normalized": [1.5] + [0.0] * 13, "steps": 2})
    assert r.status_code == 200
    assert any("outside the training range" in w for w in r.json()["warnings"])


def test_outside_training_range_warns(client, default_controls):
    from nemsim.controls import CONTROL_SPECS

    spec = next(s for s in CONTROL_SPECS if s.name == "flux_cl")
    r = client.post(
        "/rollout", json={"controls": {**default_controls, "flux_cl": spec.high * 10}, "steps": 1}
    )
    assert r.status_code == 200
    assert len(r.json()["warnings"]) == 1 and "flux_cl" in r.json()["warnings"][0]


def test_fields_final_and_all(client, default_controls, decode_fields, tiny_scene):
    final = client.post("/rollout", json={"controls": default_controls, "steps": 2, "fields": "final"}).json()
    f = decode_fields(final["fields"])
    assert f.shape == (1, *tiny_scene.state_shape) and final["fields"]["steps"] == [2]
    assert np.isfinite(f).all()
    everything = client.post(
        "/rollout", json={"controls": default_controls, "steps": 2, "fields": "all"}
    ).json()
    a = decode_fields(everything["fields"])
    assert a.shape == (3, *tiny_scene.state_shape)
    np.testing.assert_array_equal(a[-1], f[0])
    # step 0 is the scene's initial geometry
    from nemsim.sim import initial_state

    np.testing.assert_allclose(a[0], np.asarray(initial_state(tiny_scene)), atol=1e-3)


def test_recipe(client, default_controls):
    recipe = [default_controls, {**default_controls, "flux_cl": default_controls["flux_cl"] * 2}]
    r = client.post("/rollout", json={"recipe": recipe})
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["steps"] == 2 and len(body["recipe"]) == 2
    assert body["recipe"][1]["flux_cl"] == pytest.approx(2 * default_controls["flux_cl"])
    constant = client.post("/rollout", json={"controls": default_controls, "steps": 2}).json()
    assert constant["id"] != body["id"]


def test_partial_controls_take_the_defaults(client, default_controls):
    """Two controls given: the other twelve are /model's defaults, named in `defaulted`, and the rollout is
    the very one of the full set (same id: same normalized schedule)."""
    given = {"flux_cl": 0.01, "energy_mean_ar_plus": 300.0}
    r = client.post("/rollout", json={"controls": given, "steps": 2})
    assert r.status_code == 200, r.text
    body = r.json()
    full = {**default_controls, **given}
    assert body["controls"] == pytest.approx(full)
    assert body["defaulted"] == [n for n in default_controls if n not in given]
    defaults = {c["name"]: c["default"] for c in client.get("/model").json()["controls"]}
    assert {n: body["controls"][n] for n in body["defaulted"]} == pytest.approx(
        {n: defaults[n] for n in body["defaulted"]}
    )
    same = client.post("/rollout", json={"controls": full, "steps": 2}).json()
    assert same["id"] == body["id"] and same["defaulted"] == []
    empty = client.post("/rollout", json={"controls": {}, "steps": 2}).json()
    assert empty["controls"] == pytest.approx(default_controls) and len(empty["defaulted"]) == 14


def test_partial_recipe_rows_and_simulation_jobs(client, default_controls, make_client):
    body = client.post("/rollout", json={"recipe": [{"flux_cl": 0.01}, {**default_controls}]}).json()
    assert body["recipe"][0] == pytest.approx({**default_controls, "flux_cl": 0.01})
    assert body["recipe"][1] == pytest.approx(default_controls)
    assert body["defaulted"] == [n for n in default_controls if n != "flux_cl"]
    assert (
        client.post("/rollout", json={"controls_normalized": [0.0] * 14, "steps": 1}).json()["defaulted"]
        == []
    )
    # simulator jobs share the schema: a partial set passes validation (the work bound then refuses it)
    jobs = make_client(sim_max_work=1e-9)
    r = jobs.post("/simulations", json={"controls": {"flux_cl": 0.01}, "steps": 1})
    assert r.status_code == 422 and "work of a design-centre run" in r.json()["message"]
    r = jobs.post("/simulations", json={"controls": {"flux_cll": 0.01}, "steps": 1})
    assert r.status_code == 422 and "did you mean 'flux_cl'?" in r.json()["message"]


def test_inline_meshes(client, default_controls):
    req = {
        "controls": default_controls,
        "steps": 2,
        "meshes": [
            {"step": 2, "channel": "si", "format": "ply"},
            {"step": 0, "channel": "mask", "format": "stl"},
        ],
    }
    body = client.post("/rollout", json=req).json()
    assert [m["format"] for m in body["meshes"]] == ["ply", "stl"]
    ply = base64.b64decode(body["meshes"][0]["data"])
    assert ply.startswith(b"ply")
    follow = client.get(body["meshes"][0]["url"])
    assert follow.status_code == 200 and follow.content == ply


@pytest.mark.parametrize(
    ("fmt", "media"), [("glb", "model/gltf-binary"), ("obj", "model/obj"), ("stl", "model/stl")]
)
def test_mesh_download(client, default_controls, fmt, media):
    rid = client.post("/rollout", json={"controls": default_controls, "steps": 2}).json()["id"]
    r = client.get(f"/rollouts/{rid}/mesh", params={"step": 1, "channel": "si", "format": fmt})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith(media) and len(r.content) > 100
    assert f"step1_si.{fmt}" in r.headers["content-disposition"]


def test_mesh_glb_carries_provenance(client, default_controls):
    import io

    import trimesh

    body = client.post("/rollout", json={"controls": default_controls, "steps": 2}).json()
    r = client.get(f"/rollouts/{body['id']}/mesh", params={"channel": "mask"})  # default: final step, glb
    assert r.status_code == 200
    scene = trimesh.load(io.BytesIO(r.content), file_type="glb")
    text = repr(getattr(scene, "metadata", {})) + "".join(
        repr(g.metadata) for g in getattr(scene, "geometry", {}).values()
    )
    assert body["model_id"] in text and "mask" in text


def test_mesh_unknown_id_404(client):
    r = client.get("/rollouts/deadbeef/mesh")
    assert r.status_code == 404 and "unknown rollout id" in r.json()["detail"]


@pytest.mark.parametrize(
    "params", [{"format": "fbx"}, {"channel": "resist"}, {"step": 99}, {"step": -1}, {"step": "last"}]
)
def test_mesh_bad_query_422(client, default_controls, params):
    rid = client.post("/rollout", json={"controls": default_controls, "steps": 2}).json()["id"]
    r = client.get(f"/rollouts/{rid}/mesh", params=params)
    assert r.status_code == 422, r.text
    assert r.json()["message"]


def test_concurrent_requests_are_safe(client):
    """Many requests at once: all answered, identical ones share one cached result."""
    results: list = []

    def post(k: int) -> None:
        r = client.post("/rollout", json={"controls_normalized": [k % 3 * 0.1] + [0.2] * 13, "steps": 2})
        results.append((k % 3, r.status_code, r.json().get("id")))

    threads = [threading.Thread(target=post, args=(k,)) for k in range(9)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(code == 200 for _, code, _ in results)
    ids = {}
    for k, _, rid in results:
        ids.setdefault(k, set()).add(rid)
    assert all(len(v) == 1 for v in ids.values()) and len(ids) == 3


def test_served_trajectory_is_the_rollout(served, default_controls):
    """The server's trajectory (kept in a reused buffer, stored as float16) and metrics are those of
    `nemsim.evaluation.rollout` and `measured_profile_metrics`, for consecutive rollouts of different
    lengths through the same buffer."""
    import torch

    from nemsim.controls import to_normalized
    from nemsim.evaluation.rollout import rollout
    from nemsim.geometry.profile import measured_profile_metrics
    from service.served_model import ServedModel

    s = ServedModel(served.predictor, cache_size=0)
    base = np.array(list(default_controls.values()))
    for steps, scale in ((5, 1.0), (3, 1.3), (5, 0.8)):
        raw = np.tile(base * scale, (steps, 1))
        result, cached = s.rollout(raw)
        u = torch.from_numpy(np.asarray(to_normalized(raw), dtype=np.float32))[None]
        with torch.inference_mode():
            x0 = torch.from_numpy(s.predictor.x0)[None]
            ref = rollout(s.predictor.runtime, x0, u, steps)[0].numpy()  # (T+1, 2, D, H, W)
        states = result.states.decode()  # kept compactly, decoded bit for bit
        assert not cached and states.dtype == np.float16
        np.testing.assert_array_equal(states, ref.astype(np.float16))
        for name, values in measured_profile_metrics(ref, s.scene).items():
            np.testing.assert_allclose(np.array(result.metrics[name], dtype=float), values, equal_nan=True)
    assert len(s._buffers) == 1  # one rollout at a time: one buffer, reused


def test_the_answer_does_not_wait_for_the_states_to_be_stored(served, default_controls, monkeypatch):
    """A rollout is answered before its compact cache entry is encoded: while encoding, its id resolves (a
    repeat recomputes nothing) and reading its states waits for them; once stored it is cached, bit for
    bit the states of the rollout."""
    import threading

    from service.compact_states import CompactStates
    from service.served_model import ServedModel

    s = ServedModel(served.predictor, cache_size=4)
    encode, release = CompactStates.encode, threading.Event()

    def held(states, full_size=None, fold_kind="quarter"):
        assert release.wait(30)
        return encode(states, full_size=full_size, fold_kind=fold_kind)

    monkeypatch.setattr(CompactStates, "encode", held)
    raw = np.tile(np.array(list(default_controls.values())), (4, 1))
    result, cached = s.rollout(raw)  # returns although the encoding is held
    assert not cached and not result.encoded.done() and len(result.metrics["etch_depth"]) == 5
    assert s.get_rollout(result.id) is result and s.rollout(raw) == (result, True)
    assert len(s._rollouts) == 0  # pending, not yet in the cache
    assert s._buffers == []  # its trajectory buffer is the encoder's until its states are stored
    read = threading.Thread(target=lambda: result.states)
    read.start()
    read.join(0.2)
    assert read.is_alive()  # a reader waits for the states
    release.set()
    read.join(30)
    states = result.states.decode()
    assert len(s._rollouts) == 1 and s.get_rollout(result.id) is result
    assert len(s._buffers) == 1  # given back once encoded
    ref = s.predictor.rollout(s.predictor.schedule(raw)).states  # (T+1, 2, D, H, W) float32
    np.testing.assert_array_equal(states, np.asarray(ref).astype(np.float16))


def test_non_finite_prediction_is_a_4xx_never_a_200(served, default_controls):
    """A model whose rollout turns NaN (weights damaged after the load-time check) answers 422 naming the
    step, never 200 with a warning; the server stays up."""
    import copy
    import dataclasses

    import torch
    from fastapi.testclient import TestClient

    from nemsim.inference import Predictor
    from service.config import Settings
    from service.deps import get_served_model
    from service.main import create_app
    from service.served_model import ServedModel

    loaded = served.predictor.loaded
    model = copy.deepcopy(loaded.model)
    with torch.no_grad():
        next(p for p in model.parameters() if p.numel() > 8).fill_(float("nan"))
    broken = ServedModel(Predictor(dataclasses.replace(loaded, model=model), backend="torch"), cache_size=2)
    app = create_app(Settings(warmup_steps=0, rate_limit_per_minute=0), served=broken)
    app.dependency_overrides[get_served_model] = lambda: broken
    with TestClient(app) as c:
        for _ in range(2):  # computed, then from the cache: the same answer
            r = c.post("/rollout", json={"controls": default_controls, "steps": 2})
            assert r.status_code == 422 and "not finite" in r.json()["message"], r.text
        assert c.get("/health").status_code == 200


def test_a_rollout_request_normalizes_and_hashes_once(make_client, served, default_controls, monkeypatch):
    """POST /rollout converts physical controls once (normalized ones not at all: the model reads them as
    given) and computes the rollout id once, cached or not."""
    import nemsim.inference.predictor as predictor_module
    from service.served_model import ServedModel

    counts = {"normalize": 0, "denormalize": 0, "hash": 0}
    to_norm, from_norm, rid = (predictor_module.to_normalized, predictor_module.from_normalized,
                               ServedModel.rollout_id)  # fmt: skip

    def count(key, fn):
        def wrapped(*args):
            counts[key] += 1
            return fn(*args)

        return wrapped

    monkeypatch.setattr(predictor_module, "to_normalized", count("normalize", to_norm))
    monkeypatch.setattr(predictor_module, "from_normalized", count("denormalize", from_norm))
    monkeypatch.setattr(ServedModel, "rollout_id", count("hash", rid))
    c = make_client()
    physical = {"controls": {**default_controls, "flux_cl": default_controls["flux_cl"] * 1.0371}, "steps": 2}
    for _ in range(2):  # computed, then cached
        counts.update(normalize=0, denormalize=0, hash=0)
        assert c.post("/rollout", json=physical).status_code == 200
        assert counts == {"normalize": 1, "denormalize": 0, "hash": 1}
    counts.update(normalize=0, denormalize=0, hash=0)
    assert c.post("/rollout", json={"controls_normalized": [0.137] * 14, "steps": 2}).status_code == 200
    assert counts == {"normalize": 0, "denormalize": 1, "hash": 1}


def test_every_answer_says_how_far_from_the_training_data_it_lies(client, default_controls, served, tmp_path):
    """`trust`: the centre of the box is in-box (ok); half a half-width past an edge is the benchmark's
    `axis 1.5` group. Without an extrapolation benchmark of the served model nothing is measured (said so);
    with one stamped with its id, the group's measured error and the verdict come from it."""
    import json

    from nemsim.controls import CONTROL_INDEX, from_normalized, to_normalized
    from service.inverse import rollout_trust

    t = client.post("/rollout", json={"controls": default_controls, "steps": 2}).json()["trust"]
    assert t["group"] == "in-box" and t["level"] == "ok" and t["measured"] is None
    u = np.zeros(14)
    u[CONTROL_INDEX["energy_mean_cl_plus"]] = 1.4
    raw = from_normalized(u)
    far = {**default_controls, "energy_mean_cl_plus": float(raw[CONTROL_INDEX["energy_mean_cl_plus"]])}
    t = client.post("/rollout", json={"controls": far, "steps": 2}).json()["trust"]
    assert t["group"] == "axis 1.5" and t["box_distance"] == pytest.approx(0.4, abs=1e-3)
    assert t["level"] == "warn" and "no extrapolation benchmark" in t["reason"]

    scene = served.predictor.scene.name
    groups = {"in-box": 1.0, "axis 1.5": 2.5}
    summary = {"in_box_avg_rmse": 0.01, "groups": {
        g: {"n": 4, "avg_rmse": 0.01 * r, "ratio_to_in_box": r, "mae_nm": {"etch_depth": 3.0},
            "seed_diff_nm": {"etch_depth": 1.0}} for g, r in groups.items()}}
    path = tmp_path / scene / "extrapolation" / "extrapolation.json"
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"checkpoint_id": served.model_id.rpartition("@")[2], "summary": summary}))
    got = rollout_trust(served, raw[None], to_normalized(raw[None]), benchmarks=tmp_path)
    assert got["level"] == "warn" and got["measured"]["ratio_to_in_box"] == 2.5
    assert got["measured"]["mae_nm"] == {"etch_depth": 3.0}
    assert served.model_id in got["measured"]["source"]
    other = tmp_path / "other"  # another root: read afresh
    (other / scene / "extrapolation").mkdir(parents=True)
    (other / scene / "extrapolation" / "extrapolation.json").write_text(
        json.dumps({"checkpoint_id": "another", "summary": summary}))
    not_its_model = rollout_trust(served, raw[None], to_normalized(raw[None]), benchmarks=other)
    assert not_its_model["measured"] is None


def test_large_bodies_share_a_response_budget(make_client, default_controls, decode_fields):
    """Every field and meshes stream within the response budget: a body that does not fit beside those in
    flight gets 503 + Retry-After; once they are sent it is answered in full (meshes byte for byte as
    GET /mesh serves them) and the budget is whole again."""
    c = make_client(response_max_mb=1)
    budget = c.app.state.response_budget
    body = {"controls": default_controls, "steps": 2, "fields": "all",
            "meshes": [{"step": 2, "channel": "si", "format": "ply"}]}
    assert budget.reserve(budget.max_bytes)  # bodies in flight, the budget used up
    r = c.post("/rollout", json=body)
    assert r.status_code == 503 and r.headers["retry-after"] == "1", r.text[:300]
    budget.release(budget.max_bytes)
    r = c.post("/rollout", json=body)
    assert r.status_code == 200 and int(r.headers["content-length"]) == len(r.content)
    out = r.json()
    assert decode_fields(out["fields"]).shape[0] == 3
    [mesh] = out["meshes"]
    assert base64.b64decode(mesh["data"]) == c.get(mesh["url"]).content
    assert budget.used == 0
