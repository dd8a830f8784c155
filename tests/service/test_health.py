"""GET /health, /ready, /model; settings and start-up without a usable checkpoint."""

from __future__ import annotations

import time

from fastapi.testclient import TestClient

from service.config import Settings, default_checkpoint, get_settings
from service.main import create_app


def test_health(client):
    r = client.get("/health")
    assert r.status_code == 200 and r.json()["status"] == "ok"


def test_ready_after_warmup(client):
    r = client.get("/ready")
    assert r.status_code == 200
    assert r.json()["status"] == "ready" and r.json()["model_id"].startswith("tiny_nemsim@")


def test_model_info(client, tiny_scene):
    from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS

    info = client.get("/model").json()
    assert info["model_name"] == "nemsim" and info["checkpoint"] == "tiny_nemsim.pt"
    assert info["scene"]["name"] == "tiny" and info["scene"]["state_shape"] == list(tiny_scene.state_shape)
    assert len(info["rules_sha256"]) == 64
    assert info["metrics"] == {"avg_rmse": 0.5} and info["summary"]["note"].startswith("untrained")
    assert info["n_params"] > 0 and info["max_steps"] == 100 and info["horizon_steps"] == 100
    assert [c["name"] for c in info["controls"]] == list(CONTROL_NAMES)
    for c, spec in zip(info["controls"], CONTROL_SPECS, strict=True):
        assert set(c) >= {"name", "unit", "min", "max", "train_min", "train_max"}
        assert c["unit"] == spec.unit and (c["train_min"], c["train_max"]) == (spec.low, spec.high)
        assert c["min"] is None or c["min"] <= c["train_min"]


def test_not_ready_without_checkpoint(tmp_path):
    """A missing checkpoint never crashes the process: /health alive, /ready and model routes 503."""
    app = create_app(Settings(checkpoint=tmp_path / "missing.pt"))
    with TestClient(app) as c:
        assert c.get("/health").status_code == 200
        for _ in range(200):
            ready = c.get("/ready")
            if ready.json()["status"] == "failed":
                break
            time.sleep(0.01)
        assert ready.status_code == 503 and "missing.pt" in ready.json()["detail"]
        r = c.post("/rollout", json={"controls_normalized": [0.0] * 14, "steps": 1})
        assert r.status_code == 503 and "not ready" in r.json()["detail"]
        assert c.get("/model").status_code == 503


def test_settings_from_env(monkeypatch, tmp_path):
    monkeypatch.setenv("NEMSIM_MAX_STEPS", "250")
    monkeypatch.setenv("NEMSIM_CHECKPOINT", str(tmp_path / "x.pt"))
    get_settings.cache_clear()
    try:
        s = get_settings()
        assert s.max_steps == 250 and s.resolved_checkpoint() == tmp_path / "x.pt"
        assert get_settings() is s  # cached
    finally:
        get_settings.cache_clear()


def test_default_checkpoint_is_first_pt(monkeypatch, tmp_path):
    import service.config as config

    (tmp_path / "b_model.pt").write_bytes(b"")
    (tmp_path / "a_model.pt").write_bytes(b"")
    monkeypatch.setattr(config, "checkpoint_dirs", lambda: [tmp_path / "nothing", tmp_path])
    assert default_checkpoint() == tmp_path / "a_model.pt"
    monkeypatch.setattr(config, "checkpoint_dirs", lambda: [tmp_path / "nothing"])
    assert default_checkpoint() is None


def test_default_checkpoint_is_the_shipped_one_beside_references(monkeypatch, tmp_path):
    import service.config as config

    # "nemsim-small-k1.pt" sorts before "nemsim-small.pt": the served name wins, not the sort order
    (tmp_path / "nemsim-small-k1.pt").write_bytes(b"")
    (tmp_path / config.SHIPPED_CHECKPOINT).write_bytes(b"")
    monkeypatch.setattr(config, "checkpoint_dirs", lambda: [tmp_path])
    assert default_checkpoint() == tmp_path / config.SHIPPED_CHECKPOINT


def test_openapi_docs(client):
    assert client.get("/docs").status_code == 200
    schema = client.get("/openapi.json").json()
    controls = schema["components"]["schemas"]["Controls"]["properties"]
    assert controls["flux_cl"]["unit"] and controls["flux_cl"]["minimum"] == 0
