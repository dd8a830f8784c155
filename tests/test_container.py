"""The service image (Dockerfile), built and run: it answers /ready and one POST /rollout.

Opt-in: runs only with NEMSIM_CONTAINER_TESTS=1 and a container daemon that answers `docker info`
(building the image takes minutes; the tests' own rule of seconds and the `tiny` scene cannot hold for an
image that serves the shipped `small` checkpoint). Settings, all from the environment:

* NEMSIM_CONTAINER_IMAGE: the image tag (default `nemsim`); an existing image is reused, else built.
* NEMSIM_CONTAINER_REBUILD=1: build even when the tag exists (the layer cache keeps it quick when nothing
  changed).
* NEMSIM_CONTAINER_BASE: the build's BASE_IMAGE (default: the Dockerfile's, python:3.11-slim); without a
  registry, the Debian base of docker/build-base.sh, e.g. nemsim-base:bookworm.
* NEMSIM_CONTAINER_CLI: the container CLI (default docker; podman takes the same commands).

The container publishes its port 8000 on a free loopback port of the host and gets an API key, so the checks
run as a remote client would: a POST without the key is refused (401), /ready names the model of the repo's
checkpoint, and a 10-step rollout of the defaults that GET /model lists has the right clock, echoes its
controls, etches deeper at every step and is answered from the cache the second time. The container is
removed afterwards, also when a check fails (its log tail is in the failure message).
"""

from __future__ import annotations

import hashlib
import math
import os
import secrets
import shutil
import subprocess
import time
from collections.abc import Iterator
from itertools import pairwise
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CLI = os.environ.get("NEMSIM_CONTAINER_CLI", "docker")
IMAGE = os.environ.get("NEMSIM_CONTAINER_IMAGE", "nemsim")
CHECKPOINT = ROOT / "checkpoints" / "nemsim-small.pt"  # what the image serves (Dockerfile: cwd /app)
READY_TIMEOUT_S = 300.0  # checkpoint load, OpenVINO compilation and the warm-up rollout on a slow CPU
BUILD_TIMEOUT_S = 3600.0
STEPS = 10


def _cli(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([CLI, *args], capture_output=True, text=True, timeout=timeout, check=False)


def _daemon_answers() -> bool:
    if shutil.which(CLI) is None:
        return False
    try:
        return _cli("info", timeout=20.0).returncode == 0
    except subprocess.TimeoutExpired:
        return False


pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        os.environ.get("NEMSIM_CONTAINER_TESTS") != "1",
        reason="container tests: set NEMSIM_CONTAINER_TESTS=1",
    ),
]


def _ensure_image() -> None:
    if os.environ.get("NEMSIM_CONTAINER_REBUILD") != "1" and _cli("image", "inspect", IMAGE).returncode == 0:
        return
    args = ["build", "-t", IMAGE]
    if base := os.environ.get("NEMSIM_CONTAINER_BASE"):
        args += ["--build-arg", f"BASE_IMAGE={base}"]
    done = _cli(*args, str(ROOT), timeout=BUILD_TIMEOUT_S)
    tail = f"{done.stdout[-3000:]}{done.stderr[-3000:]}"
    assert done.returncode == 0, f"`{CLI} {' '.join(args)} .` failed:\n{tail}"


def _logs(container: str) -> str:
    done = _cli("logs", "--tail", "40", container)
    return f"\n--- container log (tail) ---\n{done.stdout}{done.stderr}"


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[str, str, str]]:
    """(base URL, API key, container id) of a running container of the image."""
    if not _daemon_answers():
        pytest.skip(f"no container daemon answers `{CLI} info`")
    _ensure_image()
    key = secrets.token_hex(16)
    started = _cli("run", "-d", "-p", "127.0.0.1::8000", "-e", f"NEMSIM_API_KEYS={key}", IMAGE)
    assert started.returncode == 0, started.stderr
    container = started.stdout.strip()
    try:
        port = _cli("port", container, "8000/tcp").stdout.split()[0].rsplit(":", 1)[1]
        yield f"http://127.0.0.1:{port}", key, container
    finally:
        _cli("rm", "-f", container)


def _wait_ready(base: str, container: str) -> dict:
    import httpx

    deadline = time.monotonic() + READY_TIMEOUT_S
    while time.monotonic() < deadline:
        running = _cli("inspect", "-f", "{{.State.Running}}", container).stdout.strip()
        assert running == "true", f"the container stopped before /ready answered 200{_logs(container)}"
        try:
            r = httpx.get(f"{base}/ready", timeout=5.0)
            if r.status_code == 200:
                return r.json()
        except httpx.TransportError:  # the server is not listening yet
            pass
        time.sleep(0.5)
    raise AssertionError(f"/ready did not answer 200 within {READY_TIMEOUT_S:.0f} s{_logs(container)}")


def test_container_answers_ready_and_a_rollout(served: tuple[str, str, str]) -> None:
    import httpx

    base, key, container = served
    ready = _wait_ready(base, container)
    model_id = "nemsim-small@" + hashlib.sha256(CHECKPOINT.read_bytes()).hexdigest()[:12]
    assert ready["status"] == "ready"
    assert ready["model_id"] == model_id, "the image serves another checkpoint than the repo's: rebuild it"

    with httpx.Client(base_url=base, timeout=120.0) as client:
        assert client.post("/rollout", json={"steps": 1}).status_code == 401  # keys are enforced
        headers = {"X-API-Key": key}
        info = client.get("/model", headers=headers)
        assert info.status_code == 200, info.text
        controls = {c["name"]: c["default"] for c in info.json()["controls"]}
        assert len(controls) == 14 and all(v is not None for v in controls.values())

        body = {"controls": controls, "steps": STEPS}
        first = client.post("/rollout", json=body, headers=headers)
        assert first.status_code == 200, f"{first.text}{_logs(container)}"
        again = client.post("/rollout", json=body, headers=headers)
    out = first.json()
    assert out["model_id"] == model_id and out["steps"] == STEPS
    assert out["times_s"] == pytest.approx([0.1 * k for k in range(STEPS + 1)])  # transitions of 0.1 s
    assert out["controls"] == pytest.approx(controls)
    for name, values in out["metrics"].items():  # null: a width not defined yet
        assert len(values) == STEPS + 1 and all(v is None or math.isfinite(v) for v in values), name
    depth = out["metrics"]["etch_depth"]
    assert depth[0] == 0.0  # the initial state: nothing etched yet
    assert all(b > a for a, b in pairwise(depth)), depth  # deeper at every step
    assert again.status_code == 200 and again.json()["cached"] is True and again.json()["id"] == out["id"]
