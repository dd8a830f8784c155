"""Service benchmarks.

`bench_service`: latency of POST /rollout through the whole app stack (in-process ASGI client, no
network). Uncached requests use distinct controls drawn uniformly in the normalized design box (seeded),
so every one is a real rollout; the cached figure repeats one request. Reported: p50/p95/mean in ms, the
CPU milliseconds per request (this process: client and server), and for the uncached requests the share
of the wall time spent outside the model's rollout (1 - rollout_ms / latency, per request): a ratio that
stays meaningful on a machine shared with other work, where absolute times are not.

`bench_load`: a live `nemsim serve` on a loopback port under `clients` concurrent HTTP clients for a
fixed time, each drawing requests from `ROUTE_MIX` (uncached and cached rollouts, meshes of finished
rollouts, cached /mechanisms, /health). Reported per route: p50/p95/p99 of the answered (200) requests
and the status counts; errors (5xx other than the 503 of a full queue, transport failures); uncached
rollouts per second; the server's RSS, peak RSS and CPU seconds.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from service.protocol import free_port


def _percentiles(samples_s: list[float]) -> dict[str, float]:
    ms = np.asarray(samples_s) * 1e3
    return {
        "n": int(ms.size),
        "p50_ms": float(np.percentile(ms, 50)),
        "p95_ms": float(np.percentile(ms, 95)),
        "mean_ms": float(ms.mean()),
    }


def bench_service(
    checkpoint: str | Path, *, n: int = 20, n_cached: int = 200, steps: int = 100, seed: int = 0,
    sim_cases: int = 0,
) -> dict[str, Any]:
    """Time `n` uncached and `n_cached` cached POST /rollout calls (metrics only) on `checkpoint`; then, with
    `sim_cases` > 0, the full-domain simulator (the checkpoint's data configuration, one core) on the first
    `sim_cases` of the same uncached recipes, and the speed-up: its median wall time over the uncached p50
    (`simulator_speedup`, the service's end-to-end speed against the simulator measured in the same run)."""
    from fastapi.testclient import TestClient

    from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, from_normalized
    from service.config import Settings
    from service.main import create_app

    settings = Settings(
        checkpoint=Path(checkpoint),
        max_steps=max(steps, 100),
        cache_size=max(n + 2, 8),
        rate_limit_per_minute=0,  # the benchmark is one client sending as fast as it can
    )
    app = create_app(settings)
    rng = np.random.default_rng(seed)

    def body(raw: np.ndarray) -> dict[str, Any]:
        for i, spec in enumerate(CONTROL_SPECS):
            if spec.kind == "int":
                raw[i] = round(raw[i])
        return {"controls": dict(zip(CONTROL_NAMES, map(float, raw), strict=True)), "steps": steps}

    with TestClient(app, base_url="http://localhost") as client:  # a Host the keyless server answers
        deadline = time.monotonic() + 600
        while client.get("/ready").status_code != 200:
            if time.monotonic() > deadline or app.state.service.status == "failed":
                raise RuntimeError(f"service not ready: {app.state.service.status} {app.state.service.error}")
            time.sleep(0.05)
        info = client.get("/model").json()
        first = body(np.asarray(from_normalized(np.zeros(len(CONTROL_NAMES))), dtype=np.float64))
        _post(client, first)  # warm the cache for the repeat figure
        recipes = [body(np.asarray(from_normalized(rng.uniform(-1, 1, len(CONTROL_NAMES)))))
                   for _ in range(n)]
        cpu0 = time.process_time()
        uncached = [_post(client, r) for r in recipes]
        cpu1 = time.process_time()
        cached = [_post(client, first) for _ in range(n_cached)]
        cpu2 = time.process_time()
    outside = [1.0 - rollout_s / wall_s for wall_s, rollout_s in uncached]
    sim = _time_simulator(checkpoint, [r["controls"] for r in recipes[:sim_cases]]) if sim_cases > 0 else None
    p50_s = float(np.percentile([wall for wall, _ in uncached], 50))
    return {
        "checkpoint": Path(checkpoint).name,  # the file name: reports carry no machine paths
        "model_id": info["model_id"],
        "steps": steps,
        "machine": _machine(settings.runtime_backend),
        "runtime": info["runtime"],  # what rolled out (GET /model): backend, precision, the CPU's flags
        "uncached": {
            **_percentiles([wall for wall, _ in uncached]),
            "cpu_ms_per_request": 1e3 * (cpu1 - cpu0) / n,
            "rollout_p50_ms": float(np.percentile([r for _, r in uncached], 50)) * 1e3,
            "outside_rollout_share_p50": float(np.percentile(outside, 50)),
            "outside_rollout_p50_ms": float(np.percentile([w - r for w, r in uncached], 50)) * 1e3,
        },
        "cached": {
            **_percentiles([wall for wall, _ in cached]),
            "cpu_ms_per_request": 1e3 * (cpu2 - cpu1) / n_cached,
        },
        **({"simulator": sim, "simulator_speedup": sim["median"]["wall_s"] / p50_s} if sim else {}),
    }


def _time_simulator(checkpoint: str | Path, controls: list[dict[str, float]]) -> dict[str, Any]:
    """``bench.sim_speed.bench_speed`` of the full-domain simulator (the checkpoint's data configuration) on
    these recipes (physical controls by name)."""
    from bench.sim_speed import bench_speed
    from nemsim.analysis.inverse.context import simulator_config
    from nemsim.controls import CONTROL_NAMES
    from nemsim.geometry.feature import Feature
    from nemsim.inference.checkpoint import load_checkpoint
    from nemsim.inference.predictor import served_scene

    loaded = load_checkpoint(checkpoint)
    config = simulator_config(loaded)
    if config is not None:  # the full-domain simulator whatever domain made the data
        config = dataclasses.replace(config, domain="full")
    scene = served_scene(loaded)  # a trench model's trench, simulated in 3-D
    design = np.array([[c[name] for name in CONTROL_NAMES] for c in controls], dtype=np.float64)
    rep = bench_speed(scene, loaded.rules, design, config)
    feature = Feature.of(scene)
    return {"domain": "full", "feature": f"{feature.kind}, cd {feature.cd_nm:g} nm, mask {feature.mask_nm:g} "
            "nm",
            "n_cases": rep["n_cases"], "median": rep["median"],
            "cases": [{"wall_s": r["wall_s"], "cpu_s": r["cpu_s"]} for r in rep["cases"]]}


def _machine(backend: str) -> dict[str, Any]:
    """Where the figures were measured: the CPU, the rollout runtime and, on CUDA, the GPU."""
    from bench.machine import cpu_name

    out: dict[str, Any] = {"cpu": cpu_name(), "cpu_count": os.cpu_count(), "runtime_backend": backend}
    if backend == "cuda":
        import torch

        if torch.cuda.is_available():
            out["gpu"] = torch.cuda.get_device_name()
    return out


def _post(client: Any, body: dict[str, Any]) -> tuple[float, float]:
    """(latency, the server's model rollout time) of one POST /rollout, seconds."""
    t0 = time.perf_counter()
    r = client.post("/rollout", json=body)
    elapsed = time.perf_counter() - t0
    if r.status_code != 200:
        raise RuntimeError(f"POST /rollout returned {r.status_code}: {r.text[:300]}")
    return elapsed, r.json()["timings"]["rollout_ms"] / 1e3


# --- load benchmark against a live server ----------------------------------------------------------

ROUTE_MIX = (  # (route label, weight): what each client picks per request
    ("POST /rollout uncached", 2),
    ("POST /rollout cached", 4),
    ("GET /rollouts/{id}/mesh", 3),
    ("GET /mechanisms cached", 2),
    ("GET /health", 1),
)


def _proc_stats(pid: int) -> dict[str, float]:
    """RSS, peak RSS (MB) and CPU seconds (user + system) of a process, from /proc (Linux)."""
    status = dict(
        line.split(":", 1) for line in open(f"/proc/{pid}/status").read().splitlines() if ":" in line
    )
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    ticks = float(os.sysconf("SC_CLK_TCK"))
    return {
        "rss_mb": int(status["VmRSS"].split()[0]) / 1024,
        "peak_rss_mb": int(status["VmHWM"].split()[0]) / 1024,
        "cpu_s": (int(fields[11]) + int(fields[12])) / ticks,
    }


def _pctl(samples: list[float]) -> dict[str, float]:
    ms = np.asarray(samples) * 1e3
    if ms.size == 0:
        return {"n": 0}
    return {
        "n": int(ms.size),
        "p50_ms": float(np.percentile(ms, 50)),
        "p95_ms": float(np.percentile(ms, 95)),
        "p99_ms": float(np.percentile(ms, 99)),
    }


def _start_server(checkpoint: str | Path, port: int | None,
                  env: dict[str, str] | None) -> tuple[subprocess.Popen, str]:
    """`nemsim serve` on a loopback port (a free one if None); (process, base URL)."""
    if port is None:
        port = free_port()
    server_env = {
        **os.environ,
        "NEMSIM_RATE_LIMIT_PER_MINUTE": "0",  # one address for every client: the limit would measure itself
        "NEMSIM_CACHE_SIZE": "256",
        **(env or {}),
    }
    proc = subprocess.Popen(
        [sys.executable, "-m", "nemsim.cli", "serve", "--checkpoint", str(checkpoint), "--port", str(port)],
        env=server_env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return proc, f"http://127.0.0.1:{port}"


def bench_load(
    checkpoint: str | Path,
    *,
    clients: int = 8,
    seconds: float = 60.0,
    steps: int = 100,
    seed: int = 0,
    port: int | None = None,
    env: dict[str, str] | None = None,
) -> dict[str, Any]:
    """Start `nemsim serve` on a loopback port, drive it with `clients` concurrent HTTP clients for
    `seconds` (request mix `ROUTE_MIX`), and report per route p50/p95/p99, status counts and errors
    (any 5xx other than 503, any transport failure), plus the server's RSS and CPU seconds."""
    import random
    import threading

    import httpx

    from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, from_normalized

    proc, base = _start_server(checkpoint, port, env)
    rng = np.random.default_rng(seed)

    def body(u: np.ndarray) -> dict[str, Any]:
        raw = np.asarray(from_normalized(u), dtype=np.float64)
        for i, spec in enumerate(CONTROL_SPECS):
            if spec.kind == "int":
                raw[i] = round(raw[i])
        return {"controls": dict(zip(CONTROL_NAMES, map(float, raw), strict=True)), "steps": steps}

    try:
        with httpx.Client(base_url=base, timeout=10) as http:
            deadline = time.monotonic() + 300
            while True:
                try:
                    if http.get("/ready").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("the server did not become ready")
                time.sleep(0.2)
            warm = [body(rng.uniform(-1, 1, len(CONTROL_NAMES))) for _ in range(4)]
            finished = [http.post("/rollout", json=b, timeout=300).json()["id"] for b in warm]
            http.get("/mechanisms", timeout=300)
        before = _proc_stats(proc.pid)
        lat: dict[str, list[float]] = {name: [] for name, _ in ROUTE_MIX}
        codes: dict[str, dict[str, int]] = {name: {} for name, _ in ROUTE_MIX}
        errors: list[str] = []
        lock = threading.Lock()
        stop = time.monotonic() + seconds
        names = [n for n, _ in ROUTE_MIX]
        weights = [w for _, w in ROUTE_MIX]

        def client(k: int) -> None:
            pick = random.Random(seed * 1000 + k)
            local_rng = np.random.default_rng(seed * 1000 + k)
            with httpx.Client(base_url=base, timeout=600) as http:
                while time.monotonic() < stop:
                    route = pick.choices(names, weights)[0]
                    t0 = time.perf_counter()
                    try:
                        if route == "POST /rollout uncached":
                            r = http.post("/rollout", json=body(local_rng.uniform(-1, 1, len(CONTROL_NAMES))))
                        elif route == "POST /rollout cached":
                            r = http.post("/rollout", json=pick.choice(warm))
                        elif route == "GET /rollouts/{id}/mesh":
                            params: dict[str, Any] = {
                                "step": pick.randrange(steps + 1),
                                "format": pick.choice(["glb", "stl"]),
                            }
                            r = http.get(f"/rollouts/{pick.choice(finished)}/mesh", params=params)
                        elif route == "GET /mechanisms cached":
                            r = http.get("/mechanisms")
                        else:
                            r = http.get("/health")
                        code = str(r.status_code)
                    except httpx.HTTPError as exc:
                        code = type(exc).__name__
                    dt = time.perf_counter() - t0
                    with lock:
                        codes[route][code] = codes[route].get(code, 0) + 1
                        if code == "200":
                            lat[route].append(dt)
                        elif not code.isdigit() or (code.startswith("5") and code != "503"):
                            errors.append(f"{route}: {code}")

        threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
        t_start = time.monotonic()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.monotonic() - t_start
        after = _proc_stats(proc.pid)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    uncached_ok = len(lat["POST /rollout uncached"])
    return {
        "checkpoint": Path(checkpoint).name,
        "clients": clients,
        "seconds": seconds,
        "wall_s": wall,
        "steps": steps,
        "routes": {name: {**_pctl(lat[name]), "status": codes[name]} for name in names},
        "errors": len(errors),
        "error_examples": errors[:10],
        "uncached_rollouts_per_s": uncached_ok / wall,
        "server": {
            "rss_mb_at_start": before["rss_mb"],  # loaded, warmed up, 4 rollouts and /mechanisms cached
            "rss_mb": after["rss_mb"],
            "peak_rss_mb": after["peak_rss_mb"],
            "cpu_s_during_run": after["cpu_s"] - before["cpu_s"],
        },
    }
