"""Checkpoint loading (defects 11-13): weights-only reads, failures without paths, a permanent failure
stops the server, and what /health and /model show."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
import torch
from fastapi.testclient import TestClient

from service.config import Settings
from service.main import create_app


class _Touch:
    """Pickles to `Path(marker).touch()`: running it leaves a file behind."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def _wait_failed(c, timeout_s=30.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        r = c.get("/ready")
        if r.json()["status"] == "failed":
            return r
        time.sleep(0.02)
    raise AssertionError("never failed")


def test_malicious_checkpoint_runs_no_code(tiny_checkpoint, tmp_path):
    from service.loading import CheckpointError
    from service.surrogate import Surrogate

    ckpt = torch.load(tiny_checkpoint, map_location="cpu", weights_only=True)
    marker = tmp_path / "pwned"
    ckpt["summary"] = {"note": _Touch(marker)}
    evil = tmp_path / "evil.pt"
    torch.save(ckpt, evil)
    with pytest.raises(CheckpointError, match="refused"):
        Surrogate.from_checkpoint(evil)
    assert not marker.exists()


def test_shipped_checkpoint_reads_weights_only():
    from service.config import REPO_ROOT
    from service.loading import read_checkpoint_safely

    path = REPO_ROOT / "checkpoints" / "nemsim-small.pt"  # committed with the code
    ckpt = read_checkpoint_safely(path)
    assert ckpt["model_name"] == "nemsim" and "model_state" in ckpt


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


def test_truncated_real_checkpoint(tmp_path, tiny_checkpoint):
    from service.loading import CheckpointError, read_checkpoint_safely

    data = tiny_checkpoint.read_bytes()
    path = tmp_path / "cut.pt"
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="cut.pt") as info:
        read_checkpoint_safely(path)
    assert str(tmp_path) not in str(info.value)


def test_empty_checkpoint_setting_means_default(monkeypatch):
    monkeypatch.setenv("NEMSIM_CHECKPOINT", "")
    assert Settings().checkpoint is None


def test_health_names_the_model(client):
    body = client.get("/health").json()
    assert body["status"] == "ok" and body["model_id"].startswith("tiny_nemsim@")


def test_model_info_hides_paths_and_case_lists(surrogate, make_client, monkeypatch):
    monkeypatch.setattr(
        surrogate.loaded,
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


def test_serve_exits_non_zero_when_the_model_cannot_be_rebuilt(tmp_path, tiny_checkpoint):
    """Readable but incompatible (unknown model): the server starts, fails to load, and stops itself."""
    ckpt = torch.load(tiny_checkpoint, map_location="cpu", weights_only=True)
    ckpt["model_name"] = "no-such-model"
    bad = tmp_path / "incompatible.pt"
    torch.save(ckpt, bad)
    proc = _serve(bad)
    assert proc.returncode != 0, proc.stderr[-2000:]
    assert "can never load" in proc.stderr
