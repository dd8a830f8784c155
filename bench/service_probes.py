"""`nemsim bench service --probes`: a real `nemsim serve` (default settings, loopback) under the probes
of a serving system that must hold up: quiet latency, mixed load, bursts, slow and silent sockets, a
fuzz of the request bodies, an inverse-design job, a simulator job beside interactive rollouts, every
exit path of the job children, and the peak resident memory against the documented budget.

One server (`LiveServer`) takes the probes in this order: quiet, load, burst, slowloris, silent sockets
(`bench.service_sockets`), fuzz (`bench.service_fuzz`), an inverse-design job to its end, a simulator job
beside timed rollouts (`bench.service_lifecycle`), then SIGTERM while the job runs. Two more servers, on
one jobs folder, take the kill -9 path: a job starts, the server is killed with SIGKILL, and a new server
must find the child gone and remove its folder.

Uncached rollouts use distinct controls drawn uniformly in the design box (seeded); cached ones repeat a
body already answered. Load and burst clients each use their own loopback address (127.0.0.x), as
separate clients would; the per-client limits are then those of one client each.
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import tempfile
import threading
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench.live_server import (
    LiveServer,
    centre_controls,
    client,
    count,
    job_children,
    memory_mib,
    percentiles_ms,
    random_controls,
    server_errors,
    wait_until,
)

RSS_BUDGET_BYTES = 10**9  # "a loaded `small` server under 1 GB resident" (service.config, README)


@dataclass(frozen=True)
class ProbeConfig:
    steps: int = 100  # transitions per rollout (the paper horizon)
    quiet_uncached: int = 20
    quiet_cached: int = 50
    load_clients: int = 8
    load_requests: int = 40  # per client
    burst_clients: int = 40
    burst_waves: int = 3
    slow_sockets: int = 300
    slow_cap_s: float = 60.0
    silent_sockets: int = 600
    silent_seconds: float = 30.0
    fuzz_calls: int = 10_000
    fuzz_cap_s: float = 480.0
    job_rollouts: int = 20
    job_cap_s: float = 240.0
    design_cap_s: float = 300.0  # the design job is cancelled after this
    seed: int = 0


def _rollout(http: httpx.Client, body: dict[str, Any]) -> tuple[int | str, float, dict[str, Any]]:
    t0 = time.perf_counter()
    try:
        r = http.post("/rollout", json=body)
    except httpx.HTTPError as exc:
        return type(exc).__name__, time.perf_counter() - t0, {}
    dt = time.perf_counter() - t0
    return r.status_code, dt, (r.json() if r.status_code == 200 else {})


def probe_quiet(server: LiveServer, cfg: ProbeConfig, rng: np.random.Generator) -> dict[str, Any]:
    """Sequential uncached rollouts (distinct controls) and repeats of one cached body."""
    first = {"controls": centre_controls(), "steps": cfg.steps}
    codes: dict[str, int] = {}
    with client(server) as http:
        _rollout(http, first)
        uncached, cached = [], []
        for _ in range(cfg.quiet_uncached):
            code, dt, _ = _rollout(http, {"controls": random_controls(rng), "steps": cfg.steps})
            count(codes, code)
            uncached.append(dt) if code == 200 else None
        for _ in range(cfg.quiet_cached):
            code, dt, data = _rollout(http, first)
            count(codes, code)
            cached.append(dt) if code == 200 and data.get("cached") else None
    return {"uncached": percentiles_ms(uncached), "cached": percentiles_ms(cached), "status": codes}


class _Recent:
    """The ids of the rollouts answered, newest last (a repeat moves an id to the end)."""

    def __init__(self) -> None:
        self.ids: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self.lock = threading.Lock()

    def add(self, rid: str, body: dict[str, Any]) -> None:
        with self.lock:
            self.ids.pop(rid, None)
            self.ids[rid] = body

    def pick(self, pick: random.Random, last: int) -> tuple[str, dict[str, Any]] | None:
        with self.lock:
            items = list(self.ids.items())[-last:]
        return pick.choice(items) if items else None

    def rank(self, rid: str) -> int | None:
        """1 for the newest; None if never answered."""
        with self.lock:
            keys = list(self.ids)
        return len(keys) - keys.index(rid) if rid in self.ids else None


LOAD_MIX = (("uncached", 3), ("cached", 3), ("mesh", 4))


def probe_load(server: LiveServer, cfg: ProbeConfig, recent: _Recent) -> dict[str, Any]:
    """`load_clients` clients (own addresses), each `load_requests` requests from LOAD_MIX; mesh links
    are those of the last 32 rollouts answered (a 404 there is a cache that holds fewer than it says)."""
    lat: dict[str, list[float]] = {k: [] for k, _ in LOAD_MIX}
    codes: dict[str, dict[str, int]] = {k: {} for k, _ in LOAD_MIX}
    mesh_404: list[str] = []
    not_cached = [0]
    lock = threading.Lock()

    def run(k: int) -> None:
        pick = random.Random(cfg.seed * 100 + k)
        rng = np.random.default_rng(cfg.seed * 100 + k)
        with client(server, source=f"127.0.0.{10 + k}") as http:
            for _ in range(cfg.load_requests):
                kind = pick.choices([n for n, _ in LOAD_MIX], [w for _, w in LOAD_MIX])[0]
                got = recent.pick(pick, 32 if kind == "mesh" else 16)
                kind = kind if got is not None else "uncached"
                rid, body = got if got is not None else ("", {})
                if kind == "uncached":
                    body = {"controls": random_controls(rng), "steps": cfg.steps}
                t0 = time.perf_counter()
                try:
                    if kind == "mesh":
                        fmt, channel = pick.choice(["glb", "stl"]), pick.choice(["si", "mask"])
                        url = f"/rollouts/{rid}/mesh?step={pick.randrange(cfg.steps + 1)}&format={fmt}"
                        r = http.get(f"{url}&channel={channel}")
                    else:
                        r = http.post("/rollout", json=body)
                    code: int | str = r.status_code
                except httpx.HTTPError as exc:
                    code = type(exc).__name__
                dt = time.perf_counter() - t0
                with lock:
                    count(codes[kind], code)
                    if code == 200:
                        lat[kind].append(dt)
                    if kind == "mesh" and code == 404:
                        mesh_404.append(f"{rid}: rank {recent.rank(rid)} at the answer")
                if code == 200 and kind != "mesh":
                    data = r.json()
                    recent.add(data["id"], body)
                    if kind == "cached" and not data.get("cached"):
                        with lock:
                            not_cached[0] += 1

    t0 = time.monotonic()
    threads = [threading.Thread(target=run, args=(k,)) for k in range(cfg.load_clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - t0
    total: dict[str, int] = {}
    for c in codes.values():
        for code, n in c.items():
            total[code] = total.get(code, 0) + n
    return {
        "clients": cfg.load_clients,
        "requests": sum(total.values()),
        "wall_s": wall,
        "routes": {k: {**percentiles_ms(lat[k]), "status": codes[k]} for k in codes},
        "server_errors_5xx": server_errors(total),
        "rate_limited_429": total.get("429", 0),
        "transport_failures": sum(n for c, n in total.items() if not c.isdigit()),
        "mesh_404_last_32": len(mesh_404),
        "mesh_404_examples": mesh_404[:5],
        "repeats_not_served_from_cache": not_cached[0],
    }


def _wave(
    server: LiveServer, reqs: list[tuple[str, tuple[str, str, Any]]], codes: dict[str, dict[str, int]]
) -> list[float]:
    """Send `reqs` ((kind, (method, path, JSON body))), each from its own client and address, released at
    once; count the statuses per kind into `codes`; the latencies (s)."""
    gate = threading.Barrier(len(reqs))
    lat: list[float] = []
    lock = threading.Lock()

    def one(k: int) -> None:
        kind, (method, path, body) = reqs[k]
        with client(server, source=f"127.0.1.{k + 1}") as http:
            gate.wait()
            t0 = time.perf_counter()
            try:
                code: int | str = http.request(method, path, json=body).status_code
            except httpx.HTTPError as exc:
                code = type(exc).__name__
            with lock:
                count(codes[kind], code)
                lat.append(time.perf_counter() - t0)

    threads = [threading.Thread(target=one, args=(k,)) for k in range(len(reqs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return lat


def probe_burst(server: LiveServer, cfg: ProbeConfig, recent: _Recent) -> dict[str, Any]:
    """`burst_waves` waves of `burst_clients` clients (own addresses) released at once, each sending one
    request: an uncached rollout, a cached repeat, a mesh of a recent rollout or /health in turn."""
    kinds = ("uncached", "cached", "mesh", "health")
    codes: dict[str, dict[str, int]] = {k: {} for k in kinds}
    waves = []
    rng = np.random.default_rng(cfg.seed + 7)
    pick = random.Random(cfg.seed + 7)
    for _ in range(cfg.burst_waves):
        reqs: list[tuple[str, tuple[str, str, Any]]] = []
        for k in range(cfg.burst_clients):
            kind = kinds[k % len(kinds)]
            got = recent.pick(pick, 16)
            if kind == "uncached" or got is None:
                kind = "uncached"
                body = {"controls": random_controls(rng), "steps": cfg.steps}
                reqs.append((kind, ("POST", "/rollout", body)))
            elif kind == "cached":
                reqs.append((kind, ("POST", "/rollout", got[1])))
            elif kind == "mesh":
                reqs.append((kind, ("GET", f"/rollouts/{got[0]}/mesh?step={cfg.steps}", None)))
            else:
                reqs.append((kind, ("GET", "/health", None)))
        lat = _wave(server, reqs, codes)
        waves.append({"slowest_ms": max(lat) * 1e3, **percentiles_ms(lat)})
        time.sleep(1.0)
    total: dict[str, int] = {}
    for c in codes.values():
        for code, n in c.items():
            total[code] = total.get(code, 0) + n
    return {
        "clients": cfg.burst_clients,
        "waves": waves,
        "status": codes,
        "server_errors_5xx": server_errors(total),
        "queue_full_503": total.get("503", 0),
        "transport_failures": sum(n for c, n in total.items() if not c.isdigit()),
    }


# --- the whole run ----------------------------------------------------------------------------------


def _probe(report: dict[str, Any], name: str, progress: Any, fn: Any, *args: Any, **kwargs: Any) -> Any:
    """Run one probe into report["probes"][name] with its wall time and, when its first argument is a
    server still running, the server's memory after it; an exception is recorded, not raised (the other
    probes still run)."""
    progress(f"probe {name} ...")
    t0 = time.monotonic()
    try:
        out = fn(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001 -- one failed probe must not hide the others' figures
        out = {"error": f"{type(exc).__name__}: {exc}"[:2000]}
    out["probe_wall_s"] = time.monotonic() - t0
    if args and isinstance(args[0], LiveServer) and args[0].alive():
        out["server_memory_mib_after"] = memory_mib(args[0].pid)
    report["probes"][name] = out
    progress(f"probe {name}: {time.monotonic() - t0:.0f} s")
    return out


def run_probes(
    checkpoint: str | Path,
    cfg: ProbeConfig = ProbeConfig(),
    *,
    note: str = "",
    progress: Any = lambda msg: None,
    server_env: dict[str, str] | None = None,
) -> dict[str, Any]:
    """Every probe (module docstring) against `nemsim serve` of `checkpoint`; the report (JSON-ready).
    `server_env`: NEMSIM_* settings instead of the defaults (tests: shorter timeouts), named in the report."""
    from bench.machine import cpu_name
    from bench.service_fuzz import fuzz
    from bench.service_lifecycle import (
        probe_design_job,
        probe_job_beside_rollouts,
        probe_kill9,
        probe_sigterm,
    )
    from bench.service_report import targets
    from bench.service_sockets import silent_sockets, slowloris
    from nemsim.inference.checkpoint import checkpoint_id
    from nemsim.scenes import get_scene

    tmp = Path(tempfile.mkdtemp(prefix="nemsim-probes-"))
    report: dict[str, Any] = {
        "checkpoint": Path(checkpoint).name, "checkpoint_id": checkpoint_id(checkpoint),
        "cpu": cpu_name(), "note": note,
        "server": "nemsim serve, default settings (loopback, no API key); simulator-job "
        "folders in a fresh directory (NEMSIM_JOBS_DIR)",
        "config": asdict(cfg),
        "probes": {},
        "settings_changed": dict(server_env or {}),
    }
    t_run, load_start = time.monotonic(), os.getloadavg()[0]
    server = LiveServer(checkpoint, tmp / "jobs", tmp / "server.log", server_env)
    try:
        report["ready_s"] = server.wait_ready()
        report["rss_mib_when_ready"] = memory_mib(server.pid)["rss"]
        with client(server) as http:
            model = http.get("/model").json()
        horizon = int(model["horizon_steps"])
        cfg_steps = min(cfg.steps, int(model["max_steps"]), horizon)
        if cfg_steps != cfg.steps:
            cfg = ProbeConfig(**{**asdict(cfg), "steps": cfg_steps})
            report["config"] = asdict(cfg)
        try:
            scene = get_scene(model["scene"]["name"])
        except (KeyError, ValueError):
            scene = None
        rng = np.random.default_rng(cfg.seed)
        recent = _Recent()
        _probe(report, "quiet", progress, probe_quiet, server, cfg, rng)
        _probe(report, "load", progress, probe_load, server, cfg, recent)
        _probe(report, "burst", progress, probe_burst, server, cfg, recent)
        _probe(
            report, "slowloris", progress, slowloris, server, sockets=cfg.slow_sockets, cap_s=cfg.slow_cap_s
        )
        _probe(report, "silent_sockets", progress, silent_sockets, server, sockets=cfg.silent_sockets,
               seconds=cfg.silent_seconds, steps=cfg.steps, seed=cfg.seed + 5)
        _probe(report, "fuzz", progress, fuzz, server, calls=cfg.fuzz_calls, seed=cfg.seed, scene=scene,
               max_steps=int(model["max_steps"]), horizon=horizon, time_cap_s=cfg.fuzz_cap_s)
        wait_until(lambda: not job_children(server.jobs_dir), 60.0)  # the fuzz's cancelled jobs are gone
        _probe(
            report, "design_job", progress, probe_design_job, server, steps=cfg.steps, cap_s=cfg.design_cap_s
        )
        _probe(
            report,
            "job_beside_rollouts",
            progress,
            probe_job_beside_rollouts,
            server,
            steps=cfg.steps,
            rollouts=cfg.job_rollouts,
            horizon=horizon,
            seed=cfg.seed + 11,
            cap_s=cfg.job_cap_s,
        )
        mem = memory_mib(server.pid)
        report["probes"]["memory"] = {
            "rss_mib": mem["rss"],
            "peak_rss_mib": mem["peak"],
            "budget_mib": RSS_BUDGET_BYTES / 2**20,
            "budget": "1 GB (10^9 bytes): a loaded `small` server (service.config)",
        }
        _probe(report, "sigterm", progress, probe_sigterm, server, horizon=horizon)
        _probe(
            report,
            "kill9_restart",
            progress,
            probe_kill9,
            checkpoint,
            tmp / "jobs-kill9",
            tmp,
            horizon=horizon,
        )
    finally:
        server.stop(signal.SIGKILL)
        shutil.rmtree(tmp, ignore_errors=True)
    report["wall_s"] = time.monotonic() - t_run
    report["load_average_1min"] = {"start": load_start, "end": os.getloadavg()[0]}  # the machine's other work
    report["targets"] = targets(report, RSS_BUDGET_BYTES)
    return report
