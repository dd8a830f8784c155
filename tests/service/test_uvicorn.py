"""One real server: uvicorn on a free loopback port, spoken to over HTTP."""

from __future__ import annotations

import threading
import time

import httpx
import uvicorn

from service.protocol import free_port


def test_real_uvicorn(tiny_checkpoint, default_controls):
    from service.config import Settings
    from service.main import create_app

    port = free_port()
    app = create_app(Settings(checkpoint=tiny_checkpoint, warmup_steps=1, max_body_bytes=4096))
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=base, timeout=30) as http:
            deadline = time.monotonic() + 60
            while True:
                try:
                    ready = http.get("/ready")
                    if ready.status_code == 200:
                        break
                    assert ready.json()["status"] != "failed", ready.json()
                except httpx.TransportError:
                    pass
                assert time.monotonic() < deadline, "server never became ready"
                time.sleep(0.05)
            assert http.get("/health").json()["status"] == "ok"
            r = http.post("/rollout", json={"controls": default_controls, "steps": 2})
            assert r.status_code == 200 and len(r.json()["metrics"]["etch_depth"]) == 3
            mesh = http.get(f"/rollouts/{r.json()['id']}/mesh", params={"format": "stl"})
            assert mesh.status_code == 200 and len(mesh.content) > 84
            assert (
                http.post("/rollout", json={"controls": {**default_controls, "flux_cl": -1}}).status_code
                == 422
            )
            big = http.post(
                "/rollout", content=b"{" + b" " * 10_000 + b"}", headers={"content-type": "application/json"}
            )
            assert big.status_code == 413
            assert http.get("/health").status_code == 200  # still alive
    finally:
        server.should_exit = True
        thread.join(timeout=10)
