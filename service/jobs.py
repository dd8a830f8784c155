"""Background jobs (simulator runs, inverse designs) with progress, cancellation, a bounded queue and
bounded retention.

`JobQueue` runs submitted work on `workers` threads (default one: a job takes a core), keeps at most
`max_queue` jobs waiting (more: `ServiceBusy`, answered 503 + Retry-After) and forgets finished jobs after
`keep_s` seconds or beyond the newest `keep_max`. A job's work is a function `work(job)` that reports
`job.progress` and checks `job.cancelled`; it returns the JSON result.

A job's heavy work runs in a child process (`run_child`; `service.sim_child`, a fresh interpreter: the
server holds threads and torch): the simulator of a simulator job (`simulate_and_compare`), the whole
search of a design job (`service.inverse`). So cancelling stops it at once, a crash of the numerical code
cannot take the server down, and the server's memory does not grow with a job (a design search's
gradients take hundreds of MB). The worker thread waits for the child, passes its progress on and reads
its result. The child and the queue's worker threads run at `JOB_NICE`, the server's priority
(`service.sim_child.job_priority`): a job is never starved, and one at a time takes one core. Nothing
outlives the server (`service.job_processes`): `JobQueue.open` (server start) removes the job folders
under `work_dir` that dead servers left and kills the children on SIGTERM / SIGINT; `JobQueue.close`
(shutdown) kills them.

A cancelled job (`cancel`) stays readable with status `cancelled` and no result until it is forgotten like
any finished job; cancelling a finished job changes nothing.

A client may have at most `per_client` jobs running or waiting (`TooManyJobs`, answered 429 +
Retry-After). The comparison uses the helpers of `nemsim.evaluation.truth` (per-step RMSE in normalized
SDF units) and the profile metrics of both trajectories.

Choices: one seed per job (given, default 1), not the seed pair of the benchmarks: a job answers "how far
is the surrogate from one simulator run", the page shows the per-step RMSE and the metric differences
beside it. The error mesh is the simulator's surface coloured by the surrogate's SDF sampled on it (the
surrogate's signed distance from the simulated surface, in nm): blue where the surrogate's surface lies
outside, red inside, white on it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import pickle
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from service.compact_states import CompactStates
from service.job_processes import (
    ChildrenStopped,
    SimulatorChildren,
    remove_orphaned_dirs,
    stop_children_on_signals,
)
from service.memory import release_free_memory
from service.scheduler import ServiceBusy, lower_thread_priority
from service.schemas import jsonable
from service.sim_child import ERROR_FILE, INPUT_FILE, JOB_NICE, PROGRESS_FILE

T = TypeVar("T")
log = logging.getLogger(__name__)

STATUSES = ("pending", "running", "done", "failed", "cancelled")
KINDS = ("simulation", "design")  # simulator runs (routes/jobs.py), inverse design (routes/inverse.py)
KEEP_ARTIFACTS = 4  # finished jobs whose trajectories are kept for GET /jobs/{id}/mesh
COMPARE_BLOCK = 8  # states compared at a time (`compare`)
RETRY_AFTER_S = (1, 300)  # bounds of the Retry-After of a client at its job limit


class JobCancelled(Exception):
    """The job was cancelled while running."""


class UnknownJob(KeyError):
    """No job has this id (never created, or forgotten)."""


class TooManyJobs(ServiceBusy):
    """The client already has its limit of jobs running or waiting; `retry_after_s`: a guess of when one
    is done."""

    def __init__(self, message: str, retry_after_s: int) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


@dataclass
class Job:
    id: str
    kind: str
    work: Callable[[Job], dict[str, Any]] = field(repr=False)
    created: float = field(default_factory=time.time)
    status: str = "pending"
    progress: float = 0.0
    phase: str | None = None  # what the running work is doing (its child's word)
    result: dict[str, Any] | None = None
    message: str | None = None
    finished: float | None = None
    cancel_event: threading.Event = field(default_factory=threading.Event, repr=False)
    artifacts: dict[str, Any] = field(default_factory=dict, repr=False)  # e.g. trajectories for meshes
    client: str | None = field(default=None, repr=False)  # who submitted it (None: not counted per client)
    started: float | None = None
    children: SimulatorChildren | None = field(default=None, repr=False)  # its queue's job children

    @property
    def cancelled(self) -> bool:
        return self.cancel_event.is_set()

    def as_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "kind": self.kind,
            "status": self.status,
            "progress": round(float(self.progress), 4),
            "phase": {"pending": "waiting in the queue", "running": self.phase}.get(self.status),
            "created": self.created,
            "result": self.result if self.status == "done" else None,
            "message": self.message,
        }


class JobQueue:
    """Thread-safe job store and runner (module docstring)."""

    def __init__(
        self,
        workers: int = 1,
        max_queue: int = 4,
        keep_s: float = 3600.0,
        keep_max: int = 16,
        per_client: int = 1,
        work_dir: Path | None = None,
    ):
        if workers < 1 or max_queue < 0 or keep_s <= 0 or keep_max < 1 or per_client < 1:
            raise ValueError(
                f"need workers >= 1, max_queue >= 0, keep_s > 0, keep_max >= 1, per_client >= 1; got "
                f"{workers}, {max_queue}, {keep_s}, {keep_max}, {per_client}"
            )
        self.workers, self.max_queue, self.keep_s, self.keep_max = workers, max_queue, keep_s, keep_max
        self.per_client = per_client
        self.children = SimulatorChildren(work_dir)
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._pending: list[Job] = []
        self._lock = threading.Condition()
        self._threads: list[threading.Thread] = []
        self._closed = False

    @classmethod
    def from_settings(cls, settings: Any) -> JobQueue:
        return cls(
            settings.sim_workers,
            settings.sim_queue,
            settings.jobs_keep_s,
            settings.jobs_keep_max,
            per_client=settings.jobs_per_client,
            work_dir=settings.jobs_dir,
        )

    def open(self) -> list[Path]:
        """At server start: remove the job folders that dead servers left and stop the children on
        SIGTERM / SIGINT (from the main thread only). Returns the folders removed."""
        removed = remove_orphaned_dirs(self.children.root)
        if removed:
            log.info("removed %d job folder(s) left by a server that is gone", len(removed))
        stop_children_on_signals()
        return removed

    def submit(self, kind: str, work: Callable[[Job], dict[str, Any]], client: str | None = None) -> Job:
        """Queue `work` for `client` (None: no per-client limit); TooManyJobs when the client has
        `per_client` jobs running or waiting, ServiceBusy when `max_queue` jobs are already waiting."""
        with self._lock:
            self._prune()
            if client is not None:
                self._check_client(client)
            running = sum(j.status == "running" for j in self._jobs.values())
            if len(self._pending) >= self.max_queue and running + len(self._pending) >= self.workers:
                raise ServiceBusy(
                    f"{len(self._pending)} {kind} jobs are waiting (the limit is {self.max_queue}): "
                    "retry later"
                )
            job = Job(id=secrets.token_hex(8), kind=kind, work=work, client=client, children=self.children)
            self._jobs[job.id] = job
            self._pending.append(job)
            self._start_workers()
            self._lock.notify()
            return job

    def get(self, job_id: str) -> Job:
        with self._lock:
            self._prune()
            try:
                return self._jobs[job_id]
            except KeyError:
                raise UnknownJob(job_id) from None

    def cancel(self, job_id: str, wait_s: float = 0.0) -> Job:
        """Cancel a pending or running job (a finished one is left as it is), waiting up to `wait_s` for a
        running one to stop (its child killed, its files removed): then it is `cancelled`, and stays so
        until it is forgotten like any finished job."""
        with self._lock:
            job = self.get(job_id)
            if job.status == "pending":
                self._pending.remove(job)
                self._finish(job, "cancelled", message="cancelled before it started")
            elif job.status == "running":
                job.cancel_event.set()  # the work stops at its next check; the worker marks it cancelled
                self._lock.wait_for(lambda: job.status != "running", timeout=wait_s)
            return job

    def close(self) -> None:
        """Cancel everything, kill the job children (their files removed) and stop the workers
        (tests, shutdown)."""
        with self._lock:
            self._closed = True
            for job in list(self._pending):
                self._finish(job, "cancelled", message="the server stopped")
            self._pending.clear()
            for job in self._jobs.values():
                job.cancel_event.set()
            self._lock.notify_all()
        self.children.kill_all()

    # --- internals --------------------------------------------------------------------------------
    def _check_client(self, client: str) -> None:
        mine = [j for j in self._jobs.values() if j.client == client and j.status in ("pending", "running")]
        if len(mine) < self.per_client:
            return
        now, left = time.time(), []
        for j in mine:  # a running job's remaining time from its progress so far; else a guess
            if j.status == "running" and j.started is not None and j.progress > 0.02:
                left.append((now - j.started) * (1 - j.progress) / j.progress)
        retry = min(max(math.ceil(min(left, default=10.0)), RETRY_AFTER_S[0]), RETRY_AFTER_S[1])
        raise TooManyJobs(
            f"this client already has {len(mine)} job(s) running or waiting ({', '.join(j.id for j in mine)}"
            f"; the limit is {self.per_client} per client): wait for one to finish (GET /jobs/{{id}}) or "
            "cancel it (DELETE /jobs/{id})",
            retry,
        )

    def _start_workers(self) -> None:
        self._threads = [t for t in self._threads if t.is_alive()]
        while len(self._threads) < self.workers:
            t = threading.Thread(target=self._worker, name=f"nemsim-job-{len(self._threads)}", daemon=True)
            t.start()
            self._threads.append(t)

    def _worker(self) -> None:
        lower_thread_priority(JOB_NICE)  # this thread runs jobs only: the surrogate side of a job yields too
        while True:
            with self._lock:
                while not self._pending and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                job = self._pending.pop(0)
                job.status, job.started = "running", time.time()
            try:
                result = job.work(job)
            except JobCancelled:
                with self._lock:
                    self._finish(job, "cancelled", message="cancelled while running")
            except Exception as exc:  # noqa: BLE001 -- reported on the job (one line), logged in full
                log.exception("job %s (%s) failed", job.id, job.kind)
                with self._lock:
                    self._finish(job, "failed", message=str(exc) or type(exc).__name__)
            else:
                with self._lock:
                    if job.cancelled:
                        self._finish(job, "cancelled", message="cancelled while running")
                    else:
                        job.result, job.progress = result, 1.0
                        self._finish(job, "done")
            release_free_memory()  # what a job parsed and dropped (trajectories, result files) goes back

    def _finish(self, job: Job, status: str, message: str | None = None) -> None:
        job.status, job.message, job.finished = status, message, time.time()
        if status != "done":
            job.artifacts.clear()
        self._lock.notify_all()  # a cancel waiting for the job to stop

    def _prune(self) -> None:
        now = time.time()
        done = [j for j in self._jobs.values() if j.finished is not None]
        for j in done:
            if now - j.finished > self.keep_s:  # type: ignore[operator]
                del self._jobs[j.id]
        done = [j for j in self._jobs.values() if j.finished is not None]
        for j in done[: max(0, len(done) - self.keep_max)]:  # oldest first (insertion order)
            del self._jobs[j.id]
        # trajectories are big (two compact float16 trajectories: several MB per 100-step job on `small`):
        # only the newest KEEP_ARTIFACTS finished jobs keep them (for their meshes); results stay
        done = [j for j in self._jobs.values() if j.finished is not None]
        for j in done[: max(0, len(done) - KEEP_ARTIFACTS)]:
            j.artifacts.clear()


# --- the job children -----------------------------------------------------------------------------------


class ChildFailed(RuntimeError):
    """A job's child process failed: the class name (`kind`) and text (`detail`) of its exception, or
    neither when it ended without saying why (killed: `returncode`)."""

    def __init__(self, what: str, kind: str | None, detail: str | None, returncode: int | None) -> None:
        why = f"{kind}: {detail}" if kind else f"exit code {returncode}"
        super().__init__(f"{what} failed: {why}")
        self.kind, self.detail, self.returncode = kind, detail, returncode


def run_child(
    job: Job,
    task: str,
    inputs: Any,
    read: Callable[[Path], T],
    *,
    what: str,
    share: float = 1.0,
    write: Callable[[Path], None] | None = None,
    poll_s: float = 0.05,
) -> T:
    """Run `task` of `service.sim_child` on `inputs` in a child process of the job's queue and return
    `read(job folder)` of its output. `write(job folder)` adds input files (beside `input.pkl`). The
    child's progress (0..1) becomes the job's, times `share` (never going back), and its phase the job's
    `phase`; cancelling the job kills the child. `what` names the work in messages ("the simulator").
    Raises JobCancelled, ChildFailed, and RuntimeError (no folder, no process; naming no path). The
    child's folder is removed on every path."""
    children = job.children if job.children is not None else SimulatorChildren()
    try:
        job_dir = children.make_dir()
    except OSError as exc:  # the job's message names no path
        raise RuntimeError(f"cannot create the job's folder (NEMSIM_JOBS_DIR): {exc.strerror}") from exc
    child = None
    try:
        (job_dir / INPUT_FILE).write_bytes(pickle.dumps(inputs))
        if write is not None:
            write(job_dir)
        job.phase = f"starting {what}"
        try:
            child = children.start(job_dir, task)
        except ChildrenStopped:
            raise JobCancelled from None
        except OSError as exc:
            raise RuntimeError(f"cannot start {what}: {exc.strerror or type(exc).__name__}") from exc
        while child.poll() is None:
            if job.cancelled:
                raise JobCancelled
            with contextlib.suppress(OSError, ValueError):  # not written yet
                done, _, phase = (job_dir / PROGRESS_FILE).read_text().partition("\n")
                job.progress = max(job.progress, share * float(done))
                job.phase = phase or job.phase
            time.sleep(poll_s)
        if job.cancelled or children.stopped:
            raise JobCancelled
        if child.returncode != 0:
            try:
                error = json.loads((job_dir / ERROR_FILE).read_text())
                kind, detail = str(error["type"]), str(error["message"])
            except (OSError, ValueError, TypeError, KeyError):  # killed, or died before it could say
                kind, detail = None, None
            raise ChildFailed(what, kind, detail, child.returncode)
        return read(job_dir)
    finally:
        children.finish(child, job_dir)


# --- the simulator job ---------------------------------------------------------------------------------


def run_simulator(
    job: Job,
    scene: Any,
    config: Any,
    schedule: np.ndarray,
    seed: int,
    share: float = 0.9,
    poll_s: float = 0.05,
) -> np.ndarray:
    """Simulate `schedule` (T, 14) in a child process (`run_child`); progress 0..`share`.
    Returns (T+1, 2, D, H, W) f16."""
    inputs = (scene, config, np.asarray(schedule), int(seed))
    return run_child(
        job,
        "simulate",
        inputs,
        lambda job_dir: np.load(job_dir / "states.npy"),
        what="the simulator",
        share=share,
        poll_s=poll_s,
    )


def compare(sim: CompactStates, pred: CompactStates, predictor: Any, scene: Any = None) -> dict[str, Any]:
    """Surrogate trajectory `pred` against the simulator's `sim` (both (T+1, 2, D, H, W) float16, compact),
    profile metrics by the predictor's `metrics` in `scene` (the per-case scene; None: the model's);
    JSON-ready. Works through COMPARE_BLOCK states at a time
    (every figure is per state): float32 copies of both whole trajectories and the float64 difference
    would take about 160 MB of the server's memory on `small`."""
    from nemsim.evaluation.truth import step_rmse

    rmse_parts: list[np.ndarray] = []
    sim_parts: list[dict[str, np.ndarray]] = []
    pred_parts: list[dict[str, np.ndarray]] = []
    blocks = zip(sim.blocks(COMPARE_BLOCK), pred.blocks(COMPARE_BLOCK), strict=True)
    for sim_block, pred_block in blocks:
        sim32, pred32 = sim_block.astype(np.float32), pred_block.astype(np.float32)
        rmse_parts.append(step_rmse(pred32, sim32))
        sim_parts.append(predictor.metrics(sim32, scene))
        pred_parts.append(predictor.metrics(pred32, scene))
    rmse = np.concatenate(rmse_parts)  # (T+1,)
    m_sim = {k: np.concatenate([m[k] for m in sim_parts]) for k in sim_parts[0]}
    m_pred = {k: np.concatenate([m[k] for m in pred_parts]) for k in pred_parts[0]}

    def clean(values: Any) -> list[float | None]:
        return jsonable(np.asarray(values, dtype=np.float64))  # non-finite -> None

    diff = {k: clean(np.asarray(m_pred[k]) - np.asarray(m_sim[k])) for k in m_sim}
    return {
        "rmse_per_step": clean(rmse),
        "avg_rmse": float(rmse[1:].mean()) if len(rmse) > 1 else 0.0,
        "simulator_metrics": {k: clean(v) for k, v in m_sim.items()},
        "surrogate_metrics": {k: clean(v) for k, v in m_pred.items()},
        "metric_differences": diff,  # surrogate - simulator, nm, per state
        "final_differences": {k: v[-1] for k, v in diff.items()},
        "rmse_units": "normalized SDF (SDF / d_max)",
        "metric_units": "nm",
    }


def error_mesh(sim_field: np.ndarray, pred_field: np.ndarray, scene: Any, fmt: str, meta: dict) -> bytes:
    """The simulator's zero surface of one channel coloured by the surrogate's signed distance from it.

    sim_field, pred_field: (D, H, W) normalized SDF. Vertex colours: white at 0, red where the surrogate
    says "inside material" (negative), blue "outside", saturated at one voxel."""
    from scipy.ndimage import map_coordinates

    from nemsim.geometry.frame import frame_to_index
    from nemsim.geometry.mesh import export_mesh, surface_mesh

    mesh = surface_mesh(sim_field.astype(np.float32), scene, meta)
    if len(mesh.vertices):
        zyx = frame_to_index(np.asarray(mesh.vertices), scene).T  # (3, V) padded voxel index
        err = map_coordinates(pred_field.astype(np.float32), zyx, order=1, mode="nearest")  # (V,)
        err_nm = err * float(scene.d_max_nm)
        t = np.clip(err_nm / scene.voxel_nm, -1.0, 1.0)  # (V,)
        rgb = np.ones((len(t), 3))
        rgb[:, 0] -= np.clip(t, 0, 1)  # outside: less red
        rgb[:, 1] -= np.abs(t)
        rgb[:, 2] -= np.clip(-t, 0, 1)  # inside: less blue
        colours = np.concatenate([rgb, np.ones((len(t), 1))], axis=1)
        mesh.visual.vertex_colors = (255 * colours).astype(np.uint8)  # type: ignore[union-attr]
        mesh.metadata["max_abs_error_nm"] = float(np.abs(err_nm).max())
    return export_mesh(mesh, fmt)


def simulate_and_compare(job: Job, served: Any, schedule: Any, seed: int, case: Any = None) -> dict[str, Any]:
    """The work of a simulator job: simulate `schedule` (a `ControlSchedule`) on `case` (the predictor's
    FeatureCase; None: the model's own feature; a trench on its cross-section, `Predictor.simulator_config`),
    roll the served model out on it, compare. The job keeps both trajectories compact (`CompactStates`) and
    the per-case scene for its meshes."""
    predictor = served.predictor
    case = case or predictor.case(None)
    t0 = time.perf_counter()
    config = predictor.simulator_config(case.scene)
    sim = CompactStates.encode(run_simulator(job, case.scene, config, schedule.raw, seed))
    sim_s = time.perf_counter() - t0
    result, _ = served.rollout(schedule, case)
    if job.cancelled:
        raise JobCancelled
    job.progress = 0.95
    out = compare(sim, result.states, predictor, case.scene)
    job.artifacts.update(sim=sim, pred=result.states, scene=case.scene)
    steps = schedule.steps
    out.update(
        model_id=served.model_id,
        rollout_id=result.id,
        seed=int(seed),
        steps=steps,
        times_s=result.times_s,
        simulator_s=round(sim_s, 3),
        geometry=case.feature.to_dict(),
        simulator_domain=getattr(config, "domain", "full") if config is not None else "full",
        mesh=f"/jobs/{job.id}/mesh?step={steps}&channel=si&format=glb",
    )
    return out
