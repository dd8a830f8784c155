"""A cross-section (trench) checkpoint served: its default feature is the scene's trench, holes are refused
naming the kinds it knows, and a rollout computed and stored on the cross-section comes back as full
fields, constant along the line and mirrored across it, equal to the predictor's, with its metrics and
mesh."""

from __future__ import annotations

import numpy as np


def test_the_default_feature_is_the_trench(trench_client):
    geo = trench_client.get("/model").json()["geometry"]
    assert geo["default"] == {"kind": "trench", "cd_nm": 40.0, "mask_nm": 80.0}
    assert geo["kinds"] == {"trench": {"cd_nm": [32.0, 48.0], "mask_nm": [48.0, 80.0]}}


def test_a_hole_is_refused_naming_the_kinds(trench_client, default_controls):
    r = trench_client.post("/rollout", json={"controls": default_controls, "steps": 1,
                                             "geometry": {"kind": "hole", "cd_nm": 40, "mask_nm": 80}})
    assert r.status_code == 422, r.text
    assert "trench" in r.json()["message"]


def test_a_rollout_is_a_trench_in_full_fields(trench_client, default_controls, decode_fields,
                                              tiny_section_checkpoint, tiny_scene):
    from nemsim.inference import Predictor

    body = {"controls": default_controls, "steps": 12, "fields": "all"}
    r = trench_client.post("/rollout", json=body)
    assert r.status_code == 200, r.text
    got = r.json()
    assert got["geometry"] == {"kind": "trench", "cd_nm": 40.0, "mask_nm": 80.0}
    fields = decode_fields(got["fields"]).astype(np.float32)  # (13, 2, D, H, W)
    assert fields.shape == (13, *tiny_scene.state_shape)
    assert np.array_equal(fields, np.broadcast_to(fields[..., :1, :], fields.shape))  # constant along y
    assert np.array_equal(fields, fields[..., ::-1])  # mirrored across the trench axis
    pred = Predictor.from_checkpoint(tiny_section_checkpoint, backend="torch").rollout(default_controls, 12)
    np.testing.assert_allclose(fields, pred.states.astype(np.float16).astype(np.float32), atol=2e-3)
    depth = got["metrics"]["etch_depth"]
    np.testing.assert_allclose(np.asarray(depth, dtype=float), pred.metrics["etch_depth"], atol=1e-6)
    # stored on the cross-section, served again from the cache and as a mesh
    again = trench_client.post("/rollout", json=body).json()
    assert again["id"] == got["id"] and again.get("cached", True)
    assert np.array_equal(decode_fields(again["fields"]).astype(np.float32), fields)
    mesh = trench_client.get(f"/rollouts/{got['id']}/mesh", params={"channel": "si"})
    assert mesh.status_code == 200 and len(mesh.content) > 100


def test_mechanisms_design_and_simulations_take_the_trench(trench_client, default_controls):
    """GET /mechanisms answers on the trench; a simulator job runs it (on its cross-section) to the end, and a
    design job for it is accepted."""
    import time

    r = trench_client.get("/mechanisms")
    assert r.status_code == 200, r.text
    assert len(r.json()["result"]["interventions"]) == 8
    wide = {"kind": "trench", "cd_nm": 48.0, "mask_nm": 64.0}
    created = trench_client.post("/simulations", json={"controls": default_controls, "steps": 2,
                                                       "geometry": wide})
    assert created.status_code == 202, created.text
    location = created.headers["location"]
    deadline = time.monotonic() + 120
    while (body := trench_client.get(location).json())["status"] not in ("done", "failed", "cancelled"):
        assert time.monotonic() < deadline, body
        time.sleep(0.2)
    assert body["status"] == "done", body
    design = trench_client.post("/design", json={"targets": {"etch_depth": 40}, "geometry": wide})
    assert design.status_code == 202 and design.json()["geometry"] == wide
    trench_client.delete(design.json()["location"])
