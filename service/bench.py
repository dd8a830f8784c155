"""Latency of POST /rollout through the whole app stack (in-process ASGI client, no network).

Uncached requests use distinct controls drawn uniformly in the normalized design box (seeded), so every
one is a real rollout; the cached figure repeats one request. Reported: p50/p95/mean in ms.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np


def _percentiles(samples_s: list[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    return {
        "n": int(ms.size),
        "p50_ms": float(np.percentile(ms, 50)),
        "p95_ms": float(np.percentile(ms, 95)),
        "mean_ms": float(ms.mean()),
    }


def bench_service(
    checkpoint: str | Path, *, n: int = 20, n_cached: int = 200, steps: int = 100, seed: int = 0
) -> dict[str, Any]:
    """Time `n` uncached and `n_cached` cached POST /rollout calls (metrics only) on `checkpoint`."""
    from fastapi.testclient import TestClient

    from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, from_normalized
    from service.config import Settings
    from service.main import create_app

    settings = Settings(checkpoint=Path(checkpoint), max_steps=max(steps, 100), cache_size=max(n + 2, 8))
    app = create_app(settings)
    rng = np.random.default_rng(seed)

    def body(raw: np.ndarray) -> dict[str, Any]:
        for i, spec in enumerate(CONTROL_SPECS):
            if spec.kind == "int":
                raw[i] = round(raw[i])
        return {"controls": dict(zip(CONTROL_NAMES, map(float, raw), strict=True)), "steps": steps}

    with TestClient(app) as client:
        deadline = time.monotonic() + 600
        while client.get("/ready").status_code != 200:
            if time.monotonic() > deadline or app.state.service.status == "failed":
                raise RuntimeError(f"service not ready: {app.state.service.status} {app.state.service.error}")
            time.sleep(0.05)
        model_id = client.get("/model").json()["model_id"]
        first = body(np.asarray(from_normalized(np.zeros(len(CONTROL_NAMES))), dtype=np.float64))
        _post(client, first)  # warm the cache for the repeat figure
        uncached = [
            _post(client, body(np.asarray(from_normalized(rng.uniform(-1, 1, len(CONTROL_NAMES))))))
            for _ in range(n)
        ]
        cached = [_post(client, first) for _ in range(n_cached)]
    return {
        "checkpoint": str(checkpoint),
        "model_id": model_id,
        "steps": steps,
        "uncached": _percentiles(uncached),
        "cached": _percentiles(cached),
    }


def _post(client: Any, body: dict[str, Any]) -> float:
    t0 = time.perf_counter()
    r = client.post("/rollout", json=body)
    elapsed = time.perf_counter() - t0
    if r.status_code != 200:
        raise RuntimeError(f"POST /rollout returned {r.status_code}: {r.text[:300]}")
    return elapsed
