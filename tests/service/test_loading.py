"""Checkpoint loading in the service: failures without paths, a permanent failure stops the server (also
before binding), and what /health and /model show. The loader itself: tests/inference/test_loader.py."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
import torch
from fastapi.testclient import TestClient

from service.config import Settings
from service.main import create_app


def _wait_failed(c, timeout_s=30.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        r = c.get("/ready")
        if r.json()["status"] == "failed":
            return r
        time.sleep(0.02)
    raise AssertionError("never failed")


@pytest.mark.parametrize("content", ["missing", b"", b"PK\x03\x04 truncated", os.urandom(4096)])
def test_broken_checkpoint_fails_without_leaking_paths(tmp_path, tiny_checkpoint, content):
    path = tmp_path / "secret_dir" / "broken.pt"
    path.parent.mkdir()
    if content != "missing":
        path.write_bytes(content)
    stopped = []
    app = create_app(Settings(checkpoint=path, warmup_steps=0))
    app.state.on_load_failure = lambda: stopped.append(True)
    with TestClient(app) as c:
        ready = _wait_failed(c)
        assert ready.status_code == 503
        text = ready.text + c.post("/rollout", json={"controls_normalized": [0.0] * 14, "steps": 1}).text
        assert "broken.pt" in ready.json()["detail"] and "broken.pt" in ready.json()["message"]
        assert "secret_dir" not in text and str(tmp_path) not in text
        assert "Error" not in ready.json()["detail"]  # no exception class names
    assert stopped == [True]


def test_empty_checkpoint_setting_means_default(monkeypatch):
    monkeypatch.setenv("NEMSIM_CHECKPOINT", "")
    assert Settings().checkpoint is None


def test_health_names_the_model(client):
    body = client.get("/health").json()
    assert body["status"] == "ok" and body["model_id"].startswith("tiny_nemsim@")


def test_model_info_hides_paths_and_case_lists(served, make_client, monkeypatch):
    monkeypatch.setattr(
        served.predictor.loaded,
        "metrics",
        {
            "control-id": {
                "avg_rmse": 0.1,
                "case_ids": list(range(100)),
                "cd_per_case": [0.5] * 100,
                "checkpoint": "/home/dev/runs/x/best.pt",
                "rmse_per_step": [0.1, 0.2],
            }
        },
    )
    info = make_client().get("/model").json()
    split = info["metrics"]["control-id"]
    assert split == {"avg_rmse": 0.1, "checkpoint": "best.pt", "rmse_per_step": [0.1, 0.2]}


def _serve(checkpoint: Path):
    import subprocess
    import sys

    from service.config import REPO_ROOT
    from service.protocol import free_port

    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "nemsim.cli", "serve", "--checkpoint", str(checkpoint), "--port", str(port)],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_serve_refuses_an_unreadable_checkpoint_before_binding(tmp_path):
    bad = tmp_path / "random.pt"
    bad.write_bytes(os.urandom(2048))
    proc = _serve(bad)
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert "random.pt" in proc.stderr and "Uvicorn running" not in proc.stderr


def test_serve_refuses_an_incompatible_checkpoint_before_binding(tmp_path, tiny_checkpoint):
    """Readable but impossible to rebuild (one weight missing): exit 3 with its one-line reason naming the
    weight, before binding (the model is rebuilt once before the workers start)."""
    ckpt = torch.load(tiny_checkpoint, map_location="cpu", weights_only=True)
    gone = next(iter(ckpt["model_state"]))
    ckpt["model_state"].pop(gone)
    ckpt.pop("weights_sha256")
    bad = tmp_path / "incompatible.pt"
    torch.save(ckpt, bad)
    proc = _serve(bad)
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert "incompatible.pt" in proc.stderr and f"weight '{gone}' is missing" in proc.stderr
    assert "Uvicorn running" not in proc.stderr


@pytest.mark.parametrize("damage", ["nan", "bytes"])
def test_damaged_weights_never_report_ready(tmp_path, tiny_checkpoint, damage):
    """NaN weights, or bytes overwritten inside a tensor (size unchanged): /ready stays 503 with the reason
    and the server stops; no rollout is ever answered."""
    path = tmp_path / "damaged.pt"
    if damage == "nan":
        ckpt = torch.load(tiny_checkpoint, map_location="cpu", weights_only=True)
        name = next(k for k, t in ckpt["model_state"].items() if t.is_floating_point() and t.numel() > 8)
        ckpt["model_state"][name].view(-1)[:8] = float("nan")
        torch.save(ckpt, path)
    else:
        data = bytearray(tiny_checkpoint.read_bytes())
        ckpt = torch.load(tiny_checkpoint, map_location="cpu", weights_only=True)
        big = max(ckpt["model_state"].values(), key=lambda t: t.numel())
        raw = big.contiguous().view(-1).numpy().tobytes()
        at = bytes(data).index(raw[:64])  # the tensor's bytes inside the zip (stored uncompressed)
        data[at + 16 : at + 16 + 256] = b"\x00" * 256  # finite values, but not the written ones
        path.write_bytes(bytes(data))
    stopped = []
    app = create_app(Settings(checkpoint=path, warmup_steps=0))
    app.state.on_load_failure = lambda: stopped.append(True)
    with TestClient(app) as c:
        ready = _wait_failed(c)
        assert ready.status_code == 503 and "damaged.pt" in ready.json()["detail"]
        assert "damaged" in ready.json()["detail"]
        assert c.post("/rollout", json={"controls_normalized": [0.0] * 14, "steps": 1}).status_code == 503
    assert stopped == [True]
