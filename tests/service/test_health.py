"""GET /health, /ready, /model; settings and start-up without a usable checkpoint."""

from __future__ import annotations

import time

from fastapi.testclient import TestClient

from nemsim.inference.precision import cpu_name, default_precision
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
    # what rolls out, chosen for this CPU (NEMSIM_RUNTIME_PRECISION unset: auto)
    runtime = info["runtime"]
    assert runtime["precision_requested"] == "auto" and runtime["precision"] == default_precision()
    assert runtime["cpu"] == cpu_name() and runtime["backend"] in ("openvino", "torch")
    if runtime["backend"] == "openvino":  # compiled by the warm-up: what the CPU plugin runs in
        assert runtime["inference_precision"] in ("f32", "bf16")


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


def test_default_checkpoint_is_exactly_the_scene_one(monkeypatch, tmp_path):
    """The default is `nemsim-<scene>.pt` and nothing else: another *.pt (another scene's model, a
    reference) is never chosen, and without the file the path is still that one (loading then fails)."""
    import service.config as config

    (tmp_path / "a_model.pt").write_bytes(b"")
    (tmp_path / "nemsim-small-k1.pt").write_bytes(b"")  # sorts before nemsim-small.pt
    monkeypatch.setattr(config, "checkpoint_dirs", lambda: [tmp_path / "nothing", tmp_path])
    assert default_checkpoint() == tmp_path / "nothing" / "nemsim-small.pt"
    (tmp_path / "nemsim-small.pt").write_bytes(b"")
    (tmp_path / "nemsim-tiny.pt").write_bytes(b"")
    assert default_checkpoint() == tmp_path / "nemsim-small.pt"
    assert Settings(scene="tiny").resolved_checkpoint() == tmp_path / "nemsim-tiny.pt"
    assert Settings().expected_scene() == "small" and Settings(scene="tiny").expected_scene() == "tiny"
    assert Settings(checkpoint=tmp_path / "a_model.pt").expected_scene() is None  # the operator named it
    assert Settings(checkpoint=tmp_path / "nemsim-small.pt").expected_scene() == "small"  # the default file


def _failed(app) -> dict:
    with TestClient(app) as c:
        for _ in range(500):
            ready = c.get("/ready")
            if ready.json()["status"] == "failed":
                return ready.json()
            time.sleep(0.01)
    raise AssertionError(f"never failed: {ready.json()}")


def test_missing_default_checkpoint_is_a_startup_error(monkeypatch, tmp_path, tiny_checkpoint):
    """Without `nemsim-small.pt` the server fails to start, naming the file; it does not serve the first
    *.pt it finds (here a model of another scene)."""
    import shutil

    import service.config as config

    shutil.copy(tiny_checkpoint, tmp_path / "a_tiny_model.pt")
    monkeypatch.setattr(config, "checkpoint_dirs", lambda: [tmp_path])
    stopped: list[bool] = []
    app = create_app(Settings(warmup_steps=0))
    app.state.on_load_failure = lambda: stopped.append(True)
    body = _failed(app)
    assert "nemsim-small.pt" in body["detail"] and "not found" in body["detail"] and stopped == [True]


def test_a_model_of_another_scene_is_refused(monkeypatch, tmp_path, tiny_checkpoint):
    """`nemsim-small.pt` holding a `tiny` model, or NEMSIM_SCENE naming another scene: refused at load."""
    import shutil

    import service.config as config
    from service.main import checkpoint_problem

    shutil.copy(tiny_checkpoint, tmp_path / "nemsim-small.pt")
    monkeypatch.setattr(config, "checkpoint_dirs", lambda: [tmp_path])
    body = _failed(create_app(Settings(warmup_steps=0)))
    assert "scene" in body["detail"] and "'tiny'" in body["detail"] and "'small'" in body["detail"]
    assert "scene" in checkpoint_problem(Settings(checkpoint=tmp_path / "nemsim-small.pt"))  # serve passes it
    assert "scene" in checkpoint_problem(Settings(checkpoint=tiny_checkpoint, scene="small"))
    assert checkpoint_problem(Settings(checkpoint=tiny_checkpoint)) is None
    assert checkpoint_problem(Settings(checkpoint=tiny_checkpoint, scene="tiny")) is None


def test_openapi_docs(client):
    assert client.get("/docs").status_code == 200
    schema = client.get("/openapi.json").json()
    controls = schema["components"]["schemas"]["Controls"]["properties"]
    assert controls["flux_cl"]["unit"] and controls["flux_cl"]["minimum"] == 0
