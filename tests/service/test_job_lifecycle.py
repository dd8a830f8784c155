"""Simulator jobs never outlive their server and never starve interactive rollouts.

Real `nemsim serve` processes on loopback ports: a running job's child is killed and its folder removed
on SIGTERM and SIGINT; on `kill -9` of the server the child dies too and the next server removes the
folder left behind. In-process: the folders of dead owners go at start-up, a client has at most
`jobs_per_client` jobs (429 + Retry-After beyond), jobs run at `JOB_NICE` (and keep their pace beside a
busy process) and rollouts at the server's priority.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_jobs import _blocking_work as _blocking  # tests/service is on sys.path (rootdir-relative)

from bench.live_server import LiveServer, client
from service.job_processes import SimulatorChildren, remove_orphaned_dirs
from service.jobs import Job, JobQueue, TooManyJobs, run_simulator
from service.sim_child import JOB_NICE

LINUX = sys.platform.startswith("linux")
needs_proc = pytest.mark.skipif(not LINUX, reason="reads /proc; the parent-death signal is Linux's")


def long_job(default_controls: dict) -> dict:
    """A simulator job on `tiny` of about 20 s (fluxes 100x the design centre's, every step)."""
    flux = ("flux_ar_plus", "flux_cl_plus", "flux_cl2_plus", "flux_cl")
    controls = {k: v * 100 if k in flux else v for k, v in default_controls.items()}
    return {"controls": controls, "steps": 100, "seed": 1}


# --- /proc helpers ------------------------------------------------------------------------------------


def proc_stat(pid: int) -> list[str] | None:
    """Fields 3.. of /proc/<pid>/stat (state, ppid, pgrp, session, ...), None if gone or a zombie."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return None if fields[0] in ("Z", "X") else fields


def sim_children(server_pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        stat = proc_stat(int(entry.name))
        try:
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if stat is not None and int(stat[1]) == server_pid and b"service.sim_child" in cmdline:
            out.append(int(entry.name))
    return out


def wait_for(what: str, check, timeout_s: float = 30.0, every_s: float = 0.05):
    deadline = time.monotonic() + timeout_s
    while True:
        value = check()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(every_s)


# --- a real server ------------------------------------------------------------------------------------


class Server(LiveServer):
    """`nemsim serve` on a free loopback port (``bench.live_server``), its job folders under `jobs_dir`."""

    def __init__(self, checkpoint: Path, jobs_dir: Path, log: Path) -> None:
        env = {"NEMSIM_SIM_MAX_WORK": "1000", "NEMSIM_WARMUP_STEPS": "1", "NEMSIM_RATE_LIMIT_PER_MINUTE": "0",
               "NEMSIM_ACCESS_LOG": "0", "OMP_NUM_THREADS": "1"}  # fmt: skip
        super().__init__(checkpoint, jobs_dir, log, env=env)
        self.http = client(self, timeout_s=30)

    def wait_ready(self, timeout_s: float = 180.0) -> float:
        return super().wait_ready(timeout_s)

    def start_job(self, body: dict) -> int:
        """POST /simulations; the pid of the job's child once it simulates (at JOB_NICE, in its own group)."""
        r = self.http.post("/simulations", json=body)
        assert r.status_code == 202, r.text

        def child_running() -> int | None:
            pids = sim_children(self.proc.pid)
            stat = proc_stat(pids[0]) if pids else None
            return pids[0] if stat is not None and int(stat[16]) == JOB_NICE else None  # field 19: nice

        pid = wait_for("the job's child", child_running)
        wait_for("its first transition", lambda: list(self.jobs_dir.glob("nemsim-job-*/progress")))
        stat = proc_stat(pid)
        assert stat is not None and int(stat[2]) == pid and int(stat[3]) == pid  # own group and session
        return pid

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 60.0) -> tuple[int | None, float]:
        try:
            return super().stop(sig, timeout_s)
        finally:
            self.http.close()

    def kill(self) -> None:
        self.stop(signal.SIGKILL, timeout_s=10)


def job_dirs(jobs_dir: Path) -> list[Path]:
    return sorted(jobs_dir.glob("nemsim-job-*"))


@needs_proc
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_stopped_server_leaves_no_child_and_no_files(sig, tiny_checkpoint, default_controls, tmp_path):
    jobs_dir = tmp_path / "jobs"
    server = Server(tiny_checkpoint, jobs_dir, tmp_path / "server.log")
    try:
        server.wait_ready()
        child = server.start_job(long_job(default_controls))
        assert len(job_dirs(jobs_dir)) == 1  # the job's files are where the setting says
        server.stop(sig)
    finally:
        server.kill()
    wait_for("the child to die", lambda: proc_stat(child) is None, timeout_s=10)
    assert job_dirs(jobs_dir) == []


@needs_proc
@pytest.mark.slow
def test_kill_9_kills_the_child_and_the_next_server_removes_its_files(
    tiny_checkpoint, default_controls, tmp_path
):
    jobs_dir = tmp_path / "jobs"
    server = Server(tiny_checkpoint, jobs_dir, tmp_path / "server.log")
    try:
        server.wait_ready()
        child = server.start_job(long_job(default_controls))
        server.proc.kill()
        server.proc.wait(10)
    finally:
        server.kill()
    wait_for("the child to die with its server", lambda: proc_stat(child) is None, timeout_s=10)
    left = job_dirs(jobs_dir)
    assert len(left) == 1 and (left[0] / "owner").is_file()  # nothing could remove it: the next server does

    again = Server(tiny_checkpoint, jobs_dir, tmp_path / "server2.log")
    try:
        again.wait_ready()
        assert job_dirs(jobs_dir) == []
    finally:
        again.kill()


# --- in-process ---------------------------------------------------------------------------------------


def _owned_dir(root: Path, name: str, owner: str | None) -> Path:
    path = root / f"nemsim-job-{name}"
    path.mkdir()
    if owner is not None:
        (path / "owner").write_text(owner)
    return path


def test_only_the_folders_of_dead_owners_are_removed(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    gone = _owned_dir(tmp_path, "gone", f"{dead.pid} 1")
    mine = JobQueue(work_dir=tmp_path).children.make_dir()  # this process: alive
    creating = _owned_dir(tmp_path, "creating", None)  # no owner file yet, just made
    crashed = _owned_dir(tmp_path, "crashed", None)
    os.utime(crashed, (time.time() - 3600, time.time() - 3600))
    unrelated = tmp_path / "other"
    unrelated.mkdir()
    expected = {gone, crashed}
    if LINUX:  # our pid with another start time: a pid reused after its server died
        expected.add(_owned_dir(tmp_path, "reused", f"{os.getpid()} 1"))
    assert set(remove_orphaned_dirs(tmp_path)) == expected
    assert mine.is_dir() and creating.is_dir() and unrelated.is_dir()
    assert not any(p.exists() for p in expected)


def test_a_client_at_its_job_limit_is_refused_until_one_finishes():
    jobs = JobQueue(workers=2, max_queue=4, per_client=1)
    started = threading.Event()
    try:
        first = jobs.submit("simulation", _blocking(started), client="a")
        assert started.wait(5)
        with pytest.raises(TooManyJobs, match="limit is 1 per client") as refused:
            jobs.submit("design", lambda job: {}, client="a")
        assert 1 <= refused.value.retry_after_s <= 300 and first.id in str(refused.value)
        other = jobs.submit("simulation", lambda job: {}, client="b")  # another client is not held up
        jobs.cancel(first.id)
        wait_for("the cancellation", lambda: first.status == "cancelled", timeout_s=5)
        jobs.submit("simulation", lambda job: {}, client="a")
        assert other.status in ("pending", "running", "done")
    finally:
        jobs.close()


@pytest.mark.skipif(not LINUX, reason="per-thread priorities are Linux's")
def test_jobs_run_at_the_job_priority():
    base = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    jobs = JobQueue()
    try:
        job = jobs.submit("t", lambda _: {"nice": os.getpriority(os.PRIO_PROCESS, threading.get_native_id())})
        wait_for("the job", lambda: job.status == "done", timeout_s=10)
        assert job.result == {"nice": min(19, base + JOB_NICE)}
    finally:
        jobs.close()


# loop rounds in PACE_S of wall time from `start` (epoch s) on CPU `cpu`, at a job child's priority or not
PACE = """
import os, sys, time
from service.sim_child import job_priority
start, seconds, cpu, as_job = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
os.sched_setaffinity(0, {cpu})
if as_job:
    job_priority()
time.sleep(max(0.0, start - time.time()))
end, rounds = time.perf_counter() + seconds, 0
while time.perf_counter() < end:
    sum(range(1000))
    rounds += 1
print(rounds)
"""
PACE_S = 2.0


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="pins both processes to one CPU (Linux)")
def test_a_job_keeps_its_pace_beside_a_busy_process():
    """On a core it shares with another CPU-bound process (each in a session of its own, as a job's child
    and, say, a training run are) a job's child gets about as far as that process, so its wall time at
    most doubles; at nice 19 it got about 2 % as far, at nice 2 about 60 %."""
    cpu, start = max(os.sched_getaffinity(0)), time.time() + 1.5
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", PACE, str(start), str(PACE_S), str(cpu), as_job],
            stdout=subprocess.PIPE, text=True, start_new_session=True,
        )
        for as_job in ("1", "0")
    ]
    job, other = (int(p.communicate(timeout=60)[0]) for p in procs)
    assert job >= 0.75 * other, f"the job got {job} loop rounds done, the busy process beside it {other}"


@pytest.mark.skipif(not LINUX, reason="per-thread priorities are Linux's")
def test_rollouts_run_at_the_servers_priority_by_default(make_client, default_controls, served, monkeypatch):
    seen: list[int] = []
    compute = type(served)._compute

    def spy(self, *args):
        seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))
        return compute(self, *args)

    monkeypatch.setattr(type(served), "_compute", spy)
    c = make_client()
    controls = {**default_controls, "flux_cl": default_controls["flux_cl"] * 1.0371}
    assert c.post("/rollout", json={"controls": controls, "steps": 2}).status_code == 200
    assert seen == [os.getpriority(os.PRIO_PROCESS, threading.get_native_id())]


@needs_proc
def test_second_job_of_a_client_is_429_and_cancel_kills_the_child(make_client, default_controls, tmp_path):
    c = make_client(sim_max_work=1000, jobs_dir=tmp_path)
    r = c.post("/simulations", json=long_job(default_controls))
    assert r.status_code == 202, r.text
    location = r.headers["location"]
    design = {"targets": {"etch_depth": 20}}
    for path, body in (("/simulations", long_job(default_controls)), ("/design", design)):
        refused = c.post(path, json=body)
        assert refused.status_code == 429, refused.text
        assert "limit is 1 per client" in refused.json()["message"]
        assert 1 <= int(refused.headers["retry-after"]) <= 300
    children = wait_for("the job's child", lambda: sim_children(os.getpid()))
    assert len(job_dirs(tmp_path)) == 1
    assert c.delete(location).status_code == 200
    wait_for("the cancellation", lambda: c.get(location).json()["status"] == "cancelled", timeout_s=10)
    assert proc_stat(children[0]) is None and job_dirs(tmp_path) == []
    assert c.post("/simulations", json={"controls": default_controls, "steps": 2}).status_code == 202


# --- design jobs in child processes ---------------------------------------------------------------------

DESIGN_SEARCH = {"screen": 4, "starts": 1, "iterations": 1, "batch": 4, "method": "adam"}  # seconds on tiny
ENDLESS_SEARCH = {**DESIGN_SEARCH, "iterations": 100_000}  # searches until cancelled


def _with_search(monkeypatch, search: dict) -> None:
    """POST /design bodies get this search configuration."""
    import service.routes.inverse as route

    real = route.spec_from_dict
    monkeypatch.setattr(route, "spec_from_dict", lambda d: real({**d, "search": search}))


def _poll_job(c, location: str, timeout_s: float = 180.0) -> dict:
    finished = ("done", "failed", "cancelled")
    return wait_for("the job", lambda: (b := c.get(location).json())["status"] in finished and b, timeout_s)


@needs_proc
def test_a_design_job_searches_in_a_child_process(make_client, tmp_path, monkeypatch):
    """The search runs in a child of its own (task `design`), never in the server; the child is reaped
    when it is done and its folder removed."""
    import nemsim.analysis.inverse

    started: list[tuple[subprocess.Popen, str]] = []
    start = SimulatorChildren.start

    def recorded(self, job_dir: Path, task: str = "simulate") -> subprocess.Popen:
        child = start(self, job_dir, task)
        started.append((child, task))
        return child

    def not_here(*args, **kwargs):
        raise AssertionError("the design searched in the server process")

    monkeypatch.setattr(SimulatorChildren, "start", recorded)
    monkeypatch.setattr(nemsim.analysis.inverse, "search", not_here)  # the server's; the child has its own
    _with_search(monkeypatch, DESIGN_SEARCH)
    c = make_client(jobs_dir=tmp_path)
    r = c.post("/design", json={"targets": {"etch_depth": {"value": 20, "tol": 5}}, "step": 2, "k": 2})
    assert r.status_code == 202, r.text
    done = _poll_job(c, r.headers["location"])
    assert done["status"] == "done", done
    assert done["progress"] == 1.0 and len(done["result"]["recipes"]) == 2
    [(child, task)] = started
    assert task == "design" and child.pid != os.getpid()
    assert child.returncode == 0 and proc_stat(child.pid) is None  # exited and reaped (not a zombie)
    assert job_dirs(tmp_path) == []


@needs_proc
def test_cancelling_a_design_job_kills_its_child(make_client, tmp_path, monkeypatch):
    _with_search(monkeypatch, ENDLESS_SEARCH)
    c = make_client(jobs_dir=tmp_path)
    r = c.post("/design", json={"targets": {"etch_depth": 20}, "step": 2})
    assert r.status_code == 202, r.text

    def searching() -> int | None:
        pids = sim_children(os.getpid())
        stat = proc_stat(pids[0]) if pids else None
        return pids[0] if stat is not None and int(stat[16]) == JOB_NICE else None  # field 19: nice

    pid = wait_for("the design's child", searching)
    stat = proc_stat(pid)
    assert stat is not None and int(stat[2]) == pid and int(stat[3]) == pid  # own group and session
    assert Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")[-2] == b"design"
    [folder] = job_dirs(tmp_path)
    assert (folder / "model.pt").is_file()  # the served weights, loaded by the child
    assert c.delete(r.headers["location"]).status_code == 200
    assert _poll_job(c, r.headers["location"], timeout_s=10)["status"] == "cancelled"
    assert proc_stat(pid) is None and job_dirs(tmp_path) == []


def test_a_failed_design_reports_what_the_search_raised(served, tmp_path):
    """The job's message is the search's own, as when it ran in the server."""
    from types import SimpleNamespace

    import torch

    from nemsim.analysis.intervals import Support
    from nemsim.analysis.inverse import InverseContext, search, spec_from_dict
    from service.inverse import design_work

    x0 = np.zeros((2, 3, 3, 3), dtype=np.float32)  # not the scene's shape: the first rollout fails
    loaded = served.predictor.loaded
    case = SimpleNamespace(x0=x0, scene=loaded.scene, feature=None)  # the design's FeatureCase, x0 broken
    broken = SimpleNamespace(
        predictor=SimpleNamespace(case=lambda feature: case, simulator_config=lambda scene: None,
                                  loaded=loaded),
        model_id="broken-initial-state",
    )
    spec = spec_from_dict({"targets": {"etch_depth": 20}, "step": 2, "search": DESIGN_SEARCH})
    ctx = InverseContext(
        loaded.model, loaded.scene, torch.from_numpy(x0), None, Support.from_record(None), model_id="x"
    )
    with pytest.raises(Exception) as here:  # noqa: PT011 -- whatever it is, the job must say the same
        search(ctx, spec)
    jobs = JobQueue(work_dir=tmp_path)
    try:
        options = {"seed": 0, "verify": False, "verify_top": 1, "sim_seed": 1, "sim_max_work": 20.0}
        job = jobs.submit("design", lambda j: design_work(j, broken, spec, **options))
        wait_for("the failure", lambda: job.status in ("done", "failed"), timeout_s=180)
    finally:
        jobs.close()
    assert job.status == "failed" and job.message == (str(here.value) or type(here.value).__name__)
    assert job_dirs(tmp_path) == []


def test_an_unusable_jobs_dir_fails_the_job_without_naming_a_path(tmp_path):
    not_a_dir = tmp_path / "file"
    not_a_dir.write_text("")
    job = Job(id="x", kind="simulation", work=lambda job: {}, children=SimulatorChildren(not_a_dir))
    with pytest.raises(RuntimeError, match="cannot create the job's folder") as failed:
        run_simulator(job, None, None, np.zeros((1, 14)), 0)
    assert str(tmp_path) not in str(failed.value)
