"""Jobs on a live server: a simulator job's cost to interactive rollouts, where an inverse design computes,
and what is left of the jobs on every exit path of the server.

`probe_job_beside_rollouts`: uncached rollouts timed (sequential, distinct controls) just before and then
while a simulator job runs; only the rollouts that began and ended with the job's child alive count. The
job (`job_controls`): the design centre with every flux times JOB_FLUX_SCALE, over the model's horizon, so
that it runs long enough (about 15-20 s on `small`) for the rollouts to meet the simulation itself rather
than the child's start and the job's end.

`probe_design_job`: one inverse-design job (`POST /design`, the default search; the targets are the
design centre's predicted depth and bottom width after the probes' rollout steps, reachable on any scene)
to its end: the job children it ran in, their nice and peak resident size, and the server's resident size
just before, at most while it ran (sampled every DESIGN_POLL_S) and after.

`probe_sigterm`: with a job's child running, SIGTERM the server: its exit status and time, whether it
logged the end of its shutdown, and the children and job folders left under its jobs folder.

`probe_kill9`: a new server on a fresh jobs folder starts a job and is killed with SIGKILL; how long its
child outlives it, whether the folder is left (a dead server cannot remove it), and whether the next
server on the same folder removes it at start-up.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench.live_server import (
    LiveServer,
    autogroup,
    centre_controls,
    client,
    job_children,
    job_dirs,
    memory_mib,
    nice_of,
    percentiles_ms,
    random_controls,
    wait_until,
)

JOB_SOURCE = "127.0.0.3"  # the job's client (the per-client job cap is its own)
JOB_FLUX_SCALE = 4.0  # the work grows with the total flux: 4x a design-centre run, every flux in the box
DESIGN_POLL_S = 0.2  # how often `probe_design_job` reads the job and the memory of the server and child


def job_controls() -> dict[str, float]:
    """The simulator job's controls: the design centre, fluxes times JOB_FLUX_SCALE."""
    return {k: v * JOB_FLUX_SCALE if k.startswith("flux") else v for k, v in centre_controls().items()}


def start_job(
    http: httpx.Client, server: LiveServer, steps: int, timeout_s: float = 90.0
) -> tuple[str, float]:
    """Submit a simulator job and wait until its child process runs: (job id, seconds to the child)."""
    deadline = time.monotonic() + timeout_s
    while True:
        r = http.post("/simulations", json={"controls": job_controls(), "steps": steps})
        if r.status_code == 202:
            break
        if r.status_code != 429 or time.monotonic() > deadline:  # 429: this client's previous job ends
            raise RuntimeError(f"POST /simulations answered {r.status_code}: {r.text[:300]}")
        time.sleep(1.0)
    job_id = r.json()["id"]
    t = wait_until(lambda: bool(job_children(server.jobs_dir)), max(1.0, deadline - time.monotonic()))
    if t is None:
        raise RuntimeError(
            f"job {job_id}: no simulator child appeared ({http.get(f'/jobs/{job_id}').text[:300]})"
        )
    return job_id, t


def _timed(http: httpx.Client, rng: np.random.Generator, steps: int) -> float | None:
    t0 = time.perf_counter()
    r = http.post("/rollout", json={"controls": random_controls(rng), "steps": steps})
    return time.perf_counter() - t0 if r.status_code == 200 else None


def probe_job_beside_rollouts(
    server: LiveServer, *, steps: int, rollouts: int, horizon: int, seed: int, cap_s: float
) -> dict[str, Any]:
    """Rollout p50 just before and while a simulator job runs (module docstring)."""
    rng = np.random.default_rng(seed)
    with client(server) as http, client(server, source=JOB_SOURCE) as jobs:
        before = [t for t in (_timed(http, rng, steps) for _ in range(rollouts)) if t is not None]
        during: list[float] = []
        submitted, failures, child_s = 0, 0, []
        nices: list[int | None] = []
        groups: list[str | None] = []
        deadline = time.monotonic() + cap_s
        while len(during) < rollouts and time.monotonic() < deadline:
            if not job_children(server.jobs_dir):
                _, t = start_job(jobs, server, horizon)
                submitted += 1
                child_s.append(t)
                time.sleep(1.0)  # past the child's start-up (imports), into the simulation itself
                nices += [nice_of(pid) for pid in job_children(server.jobs_dir)]
                groups += [autogroup(pid) for pid in job_children(server.jobs_dir)]
            alive_before = bool(job_children(server.jobs_dir))
            took = _timed(http, rng, steps)
            if took is None:
                failures += 1
            elif alive_before and job_children(server.jobs_dir):
                during.append(took)
    b, d = percentiles_ms(before), percentiles_ms(during)
    return {
        "rollouts_before": b,
        "rollouts_during_job": d,
        "rollout_failures": failures,
        "jobs_submitted": submitted,
        "seconds_to_child": child_s,
        "job_flux_scale": JOB_FLUX_SCALE,
        "server_nice": nice_of(server.pid),
        "job_child_nice": nices,
        "server_autogroup": autogroup(server.pid),
        "job_child_autogroup": groups,
        "p50_ratio_to_just_before": d["p50_ms"] / b["p50_ms"] if d.get("n") and b.get("n") else None,
    }


def probe_design_job(server: LiveServer, *, steps: int, cap_s: float) -> dict[str, Any]:
    """One design job for targets at state `steps` to its end, cancelled after `cap_s` (module
    docstring)."""
    with client(server, source=JOB_SOURCE) as http:
        r = http.post("/rollout", json={"controls": centre_controls(), "steps": steps})
        r.raise_for_status()
        metrics = r.json()["metrics"]
        last = {m: metrics[m][-1] for m in ("etch_depth", "bottom_width")}  # None: not defined yet
        targets = {m: round(float(v), 1) for m, v in last.items() if v is not None}
        wait_until(lambda: not job_children(server.jobs_dir), 60.0)  # the previous probe's jobs are gone
        before = memory_mib(server.pid)
        t0 = time.monotonic()
        r = http.post("/design", json={"targets": targets, "step": steps, "k": 3})
        if r.status_code != 202:
            raise RuntimeError(f"POST /design answered {r.status_code}: {r.text[:300]}")
        location = r.headers["location"]
        rss_max, children, nices, child_peak = before["rss"], set(), set(), 0.0
        while True:
            body = http.get(location).json()
            rss_max = max(rss_max, memory_mib(server.pid)["rss"])
            for pid in job_children(server.jobs_dir):
                children.add(pid)
                nices.add(nice_of(pid))
                try:
                    child_peak = max(child_peak, memory_mib(pid)["peak"])
                except OSError:  # gone meanwhile
                    pass
            if body["status"] in ("done", "failed", "cancelled"):
                break
            if time.monotonic() - t0 > cap_s:
                http.delete(location)
            time.sleep(DESIGN_POLL_S)
        wall_s = time.monotonic() - t0
        children_gone_s = wait_until(lambda: not job_children(server.jobs_dir), 15.0)
        after = memory_mib(server.pid)
    return {
        "targets": targets,
        "step": steps,
        "status": body["status"],
        "message": body["message"],
        "wall_s": wall_s,
        "recipes": len((body.get("result") or {}).get("recipes") or []),
        "job_children": len(children),
        "job_child_nice": sorted(n for n in nices if n is not None),
        "job_child_peak_rss_mib": child_peak,
        "children_gone_after_s": children_gone_s,
        "server_rss_mib": {"before": before["rss"], "max_while_running": rss_max, "after": after["rss"]},
        "server_peak_rss_mib": {"before": before["peak"], "after": after["peak"]},
    }


def probe_sigterm(server: LiveServer, *, horizon: int) -> dict[str, Any]:
    """SIGTERM with a job's child running (module docstring); stops `server`."""
    with client(server, source=JOB_SOURCE) as jobs:
        if not job_children(server.jobs_dir):
            start_job(jobs, server, horizon)
    children, folders = job_children(server.jobs_dir), job_dirs(server.jobs_dir)
    code, exit_s = server.stop(signal.SIGTERM)
    gone = wait_until(lambda: not job_children(server.jobs_dir), 10.0)
    return {
        "children_before": len(children),
        "job_folders_before": len(folders),
        "exit_status": code,
        "exit_s": exit_s,
        "children_left": len(job_children(server.jobs_dir)),
        "children_gone_after_exit_s": gone,
        "job_folders_left": len(job_dirs(server.jobs_dir)),
        # uvicorn re-raises the signal after its shutdown, so the status is -15 (143 in a shell) either way
        "graceful_shutdown": "Application shutdown complete" in server.log_path.read_text(errors="replace"),
    }


def probe_kill9(
    checkpoint: str | Path, jobs_dir: Path, log_dir: Path, *, horizon: int, env: dict[str, str] | None = None
) -> dict[str, Any]:
    """kill -9 with a job running, then a restart on the same jobs folder (module docstring)."""
    first = LiveServer(checkpoint, jobs_dir, log_dir / "server-kill9.log", env)
    try:
        first.wait_ready()
        with client(first, source=JOB_SOURCE) as jobs:
            start_job(jobs, first, horizon)
        time.sleep(1.0)
        children = job_children(jobs_dir)
        folders_before = len(job_dirs(jobs_dir))
        code, _ = first.stop(signal.SIGKILL)
    finally:
        first.stop(signal.SIGKILL)
    child_gone_s = wait_until(lambda: not job_children(jobs_dir), 15.0)
    folders_after_kill = len(job_dirs(jobs_dir))
    second = LiveServer(checkpoint, jobs_dir, log_dir / "server-restart.log", env)
    try:
        ready_s = second.wait_ready()
        folders_after_restart = len(job_dirs(jobs_dir))
        children_after_restart = len(job_children(jobs_dir))
    finally:
        second_code, _ = second.stop(signal.SIGTERM)
    return {
        "children_before_kill": len(children),
        "job_folders_before_kill": folders_before,
        "exit_status": code,
        "child_gone_after_kill_s": child_gone_s,
        "children_left_after_kill": len(job_children(jobs_dir)),
        "job_folders_left_by_the_killed_server": folders_after_kill,
        "restart_ready_s": ready_s,
        "job_folders_after_restart": folders_after_restart,
        "children_after_restart": children_after_restart,
        "restart_sigterm_exit_status": second_code,
        "job_folders_after_restart_stopped": len(job_dirs(jobs_dir)),
    }
