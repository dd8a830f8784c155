"""Fixtures for the service tests: a tiny checkpoint (untrained NEMSim on the `tiny` scene, written with
`save_checkpoint`), the ServedModel over it (fixture `served`), and TestClients.

Until a trained small checkpoint is shipped, tests make their own on `tiny`. Rollouts start from
`nemsim.sim.initial_state(scene)`, the simulator's SDF of the initial geometry.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

import numpy as np
import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(scope="session", autouse=True)
def testclient_host():
    """TestClient sends `Host: testserver`, which a server without API keys refuses (DNS-rebinding guard)
    unless allowed: every Settings() of these tests allows it (tests of the guard pass allowed_hosts)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NEMSIM_ALLOWED_HOSTS", "testserver")
        yield


@pytest.fixture(scope="session")
def served(tiny_checkpoint):
    from service.served_model import ServedModel

    s = ServedModel.from_checkpoint(tiny_checkpoint, cache_size=16)
    s.warm_up(1)  # as the server does before /ready: the runtime compiles here, not in a test's request
    return s


def wait_ready(client, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        r = client.get("/ready")
        if r.status_code == 200:
            return
        status = r.json().get("status")
        if status == "failed" or time.monotonic() > deadline:
            raise AssertionError(f"service not ready: {r.json()}")
        time.sleep(0.02)


@pytest.fixture(scope="session")
def client(tiny_checkpoint):
    """The app as deployed: settings name the checkpoint, lifespan loads it and runs the warm-up."""
    from fastapi.testclient import TestClient

    from service.config import Settings
    from service.main import create_app

    app = create_app(
        Settings(
            checkpoint=tiny_checkpoint, warmup_steps=1, max_steps=100, cache_size=16, rate_limit_per_minute=0
        )
    )
    with TestClient(app) as c:
        wait_ready(c)
        yield c


@pytest.fixture(scope="module")
def trench_client(tiny_section_checkpoint):
    """The app serving the cross-section (trench) checkpoint."""
    from fastapi.testclient import TestClient

    from service.config import Settings
    from service.main import create_app

    app = create_app(Settings(checkpoint=tiny_section_checkpoint, warmup_steps=1, max_steps=100,
                              cache_size=8, rate_limit_per_minute=0))
    with TestClient(app) as c:
        wait_ready(c)
        yield c


@pytest.fixture
def make_client(served):
    """A client over the shared served model with other settings (no reload):
    make_client(max_body_bytes=...)."""
    from fastapi.testclient import TestClient

    from service.config import Settings
    from service.deps import get_served_model
    from service.main import create_app

    clients = []

    def make(**overrides):
        # no rate limit unless a test asks: a whole test module may send hundreds of requests at once
        settings = Settings(**{"warmup_steps": 0, "rate_limit_per_minute": 0, **overrides})
        app = create_app(settings, served=served)
        app.dependency_overrides[get_served_model] = lambda: served
        c = TestClient(app)
        c.__enter__()
        clients.append(c)
        return c

    yield make
    for c in clients:
        c.__exit__(None, None, None)


@pytest.fixture(scope="session")
def default_controls():
    from service.schemas import array_to_controls, default_controls_raw

    return array_to_controls(default_controls_raw())


@pytest.fixture(scope="session")
def decode_fields():
    """payload of `fields` -> np.ndarray (n, 2, D, H, W) float16."""
    import base64

    def decode(payload: dict) -> np.ndarray:
        assert payload["dtype"] == "<f2" and payload["encoding"] == "base64"
        return np.frombuffer(base64.b64decode(payload["data"]), dtype="<f2").reshape(payload["shape"])

    return decode


@contextlib.contextmanager
def _serve_in_thread(app, settings) -> Iterator[tuple[str, int]]:
    """A real uvicorn server for ``app``, configured as `nemsim serve` configures it, in a daemon thread;
    yields (host, port) once it listens and stops it on exit."""
    import threading

    import uvicorn

    from service.protocol import free_port, uvicorn_options

    port = free_port()
    config = uvicorn.Config(
        app, host="127.0.0.1", port=port, log_level="warning", lifespan="on", **uvicorn_options(settings)
    )
    srv = uvicorn.Server(config)
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not srv.started:
        assert time.monotonic() < deadline, "server did not start"
        time.sleep(0.02)
    try:
        yield ("127.0.0.1", port)
    finally:
        srv.should_exit = True
        thread.join(timeout=10)


@pytest.fixture(scope="session")
def serve_in_thread():
    """serve_in_thread(app, settings): a context manager yielding (host, port) of a real server."""
    return _serve_in_thread
