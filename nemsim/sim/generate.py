"""Data sets: simulate many cases into one resumable HDF5 file ([supp_data_generation]).

``generate_dataset`` schedules the cases on a local process pool (default) or a Ray cluster, writes each
finished case from the parent process through ``nemsim.data.hdf5.TrajectoryWriter`` (which flags a case
complete only after its states are on disk), skips cases already complete in an existing file (resume),
shows a tqdm progress bar with ETA and validates the file on close.

Seeds: case ``c`` of a run with base seed ``S`` uses ``np.random.default_rng(case_seed(S, c))`` with
``case_seed(S, c) = SeedSequence([S, c]).generate_state(1, uint64)[0] >> 1`` (a non-negative int64); the
seed is stored per case (``seeds``) and the base seed, simulator version and all ``SimConfig`` constants in
the file's ``generator`` attribute. A case's trajectory does not depend on the worker count or the order
in which cases finish. ``seed_ids`` (the ``seed_id`` column of ``nemsim design --kind pairs``) gives a case
the seed of another case id instead of its own: the two members of a sweep pair share their random numbers
(``nemsim.controls.pair_design``), and equal stored ``seeds`` mark them in the file.

Stopping and failures: Ctrl-C and ``kill -TERM`` (turned into KeyboardInterrupt while generating) both
terminate the pool's workers and close the file with every finished case kept; workers also exit on their
own within a second once the generating process is gone (even after a SIGKILL). Any failure keeps the
finished cases; rerunning the same command resumes. Rerunning with more cases (``--n 16`` after ``--n 12``)
appends them to the file (``TrajectoryWriter``). The simulator needs no torch, so neither should a worker
(each would carry ~0.5 GB); tests/data/test_generate_robustness.py checks what a worker imports.

Geometry (``geometry`` = (kind, (N, 2) [cd_nm, mask_nm]), ``nemsim.geometry.feature``): each case is
simulated on its own per-case scene (``Feature.apply``: the scene's grid with that feature drawn); the mask
thickness is rounded to whole voxels first and the file stores the features as built (``geometry`` dataset,
``feature_kind`` attribute). Every row is checked to fit the grid before the file is touched. Without it
every case has the scene's default feature, as before.

Large scenes: the ``paper`` scene has ~7x the voxels of ``small``, so its 500 cases run for hours; the
command is resumable (rerun it after any stop) and ``state_dtype="float16"`` stores less than half the bytes
per case, far below the Monte Carlo noise (``nemsim.data.hdf5``). Example: ``nemsim generate --scene paper
--workers 2 --state-dtype float16 --out data/paper.h5`` (rerun the same command to resume), then
``nemsim data check data/paper.h5``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nemsim.geometry.feature import Feature, case_features
from nemsim.rules.compile import RuleTensors
from nemsim.scenes import Scene

from .config import SimConfig

log = logging.getLogger(__name__)

SIMULATOR_NAME = "nemsim.sim"
SIMULATOR_VERSION = "1.0"
EXECUTORS = ("process", "ray")
Executor = Literal["process", "ray"]


def case_seed(base_seed: int, case_id: int) -> int:
    """Per-case simulator seed (module docstring); independent of scheduling."""
    state = np.random.SeedSequence([int(base_seed), int(case_id)]).generate_state(1, np.uint64)[0]
    return int(state >> np.uint64(1))


def generator_meta(scene: Scene, config: SimConfig, base_seed: int) -> dict:
    """The ``generator`` attribute: simulator identity, constants and the seeding rule."""
    from nemsim import __version__

    return {
        "simulator": SIMULATOR_NAME,
        "simulator_version": SIMULATOR_VERSION,
        "package_version": __version__,
        "base_seed": int(base_seed),
        "case_seed": "SeedSequence([base_seed, case_id]).generate_state(1, uint64)[0] >> 1",
        "config": config.to_meta(scene),
    }


@dataclass(frozen=True)
class CaseTask:
    """One case to simulate (picklable; sent to workers)."""

    row: int
    case_id: int
    seed: int
    controls: np.ndarray  # (14,) or (T, 14) raw
    feature: Feature | None = None  # the case's feature (module docstring, "Geometry"); None: the scene's


def simulate_case(scene: Scene, rules: RuleTensors, config: SimConfig, task: CaseTask) -> tuple:
    """Worker body: one case -> (row, states (T+1, 2, D, H, W) float32, seed, meta)."""
    from .process import run_trajectory

    t0 = time.process_time()
    case_scene = scene if task.feature is None else task.feature.apply(scene)
    res = run_trajectory(case_scene, rules, task.controls, np.random.default_rng(task.seed), config)
    meta = {
        "case_id": task.case_id,
        "wall_s": round(res.wall_s, 3),
        "cpu_s": round(time.process_time() - t0, 3),
        "counters": res.counters,
        "event_counts": {str(n): int(v) for n, v in zip(rules.names, res.event_counts, strict=True) if v},
        "initial_totals": res.initial_totals.tolist(),
        "final_totals": res.final_totals.tolist(),
    }
    return task.row, res.states, task.seed, meta


def _worker_init(parent_pid: int | None = None) -> None:
    # one core per worker: numba kernels are single-threaded; keep BLAS/OpenMP from oversubscribing
    for var in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if parent_pid is not None:
        threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True).start()


# (scene, rules, config) of a pool worker, set once by _pool_worker_init
_WORKER_CASE: tuple[Scene, RuleTensors, SimConfig] | None = None


def _pool_worker_init(parent_pid: int, scene: Scene, rules: RuleTensors, config: SimConfig) -> None:
    """A pool worker receives the scene, rules and config once: each task is then a few hundred bytes. With
    ~55 kB tasks the call queue's pipe stays full while workers are busy, and a run stopped while the pool
    shuts down could hang at exit with the queue's feeder thread blocked on a pipe nobody reads."""
    global _WORKER_CASE
    _worker_init(parent_pid)
    _WORKER_CASE = (scene, rules, config)


def _simulate_in_worker(task: CaseTask) -> tuple:
    assert _WORKER_CASE is not None, "a pool worker is initialized by _pool_worker_init"
    scene, rules, config = _WORKER_CASE
    return simulate_case(scene, rules, config, task)


def _exit_with_parent(parent_pid: int, poll_s: float = 1.0) -> None:
    """Worker watchdog: exit as soon as the generating process is gone (even if it was SIGKILLed), instead
    of finishing a case nobody will write (the simulation loop returns to Python every macro step)."""
    while os.getppid() == parent_pid:
        time.sleep(poll_s)
    os._exit(1)


@dataclass
class _StopRequest:
    """Set by SIGTERM while generating. The pool loop polls ``requested`` (an exception raised from a signal
    handler is lost if it lands in a weakref callback or ``__del__``, as it did in the pool's wait, and
    prints a traceback); with ``raise_now`` (the serial path: the main thread is in the simulation) the
    handler raises KeyboardInterrupt at once."""

    requested: bool = False
    raise_now: bool = False

    def check(self) -> None:
        if self.requested:
            raise KeyboardInterrupt("terminated by SIGTERM")


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[_StopRequest]:
    """While generating, SIGTERM ends the run like Ctrl-C: workers terminated, the file closed with every
    finished case kept (see ``_StopRequest``); the old handler is restored afterwards."""
    stop = _StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def handler(signum, frame):
        stop.requested = True
        if stop.raise_now:
            raise KeyboardInterrupt(f"terminated by signal {signum}")

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_serial(scene, rules, config, tasks) -> Iterator[tuple]:
    for task in tasks:
        yield simulate_case(scene, rules, config, task)


def _run_process_pool(scene, rules, config, tasks, workers, stop: _StopRequest) -> Iterator[tuple]:
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")  # no fork of an open HDF5 file / torch state
    pending = list(tasks)[::-1]
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_pool_worker_init,
                               initargs=(os.getpid(), scene, rules, config))  # fmt: skip
    finished = False
    try:
        running: set[Any] = set()  # futures of the cases being simulated
        while pending or running:
            while pending and len(running) < 2 * workers:  # bound memory: states return to the parent
                running.add(pool.submit(_simulate_in_worker, pending.pop()))
            done, running = wait(running, timeout=0.5, return_when=FIRST_COMPLETED)
            stop.check()
            for fut in done:
                yield fut.result()
        finished = True
    finally:
        if finished:
            pool.shutdown(wait=True)
        else:  # interrupted or failed: do not wait for cases still running in our workers
            procs = list((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                if proc.is_alive():
                    proc.terminate()
            for proc in procs:  # a worker inside compiled code (numba's first compile) can defer SIGTERM
                proc.join(timeout=2.0)
                if proc.is_alive():
                    proc.kill()
                    proc.join(timeout=2.0)


def _run_ray(scene, rules, config, tasks, workers) -> Iterator[tuple]:
    try:
        import ray
    except ImportError as exc:
        raise RuntimeError(
            "executor 'ray' needs Ray: install it with `pip install 'nemsim[ray]'` (or `pip install ray`), "
            "or use --executor process"
        ) from exc
    started = False
    if not ray.is_initialized():
        address = os.environ.get("RAY_ADDRESS")
        ray.init(address=address, num_cpus=None if address else workers, include_dashboard=False,
                 log_to_driver=False)  # fmt: skip
        started = True
    try:
        remote = ray.remote(num_cpus=1)(simulate_case)
        shared = [ray.put(scene), ray.put(rules), ray.put(config)]
        pending = list(tasks)[::-1]
        running: list = []
        while pending or running:
            while pending and len(running) < 2 * max(workers, 1):
                running.append(remote.remote(*shared, pending.pop()))
            done, running = ray.wait(running, num_returns=1)
            for ref in done:
                yield ray.get(ref)
    finally:
        if started:
            ray.shutdown()


def generate_dataset(
    out: str | Path,
    scene: Scene,
    rules: RuleTensors,
    controls_raw: np.ndarray,
    case_ids: Sequence[int],
    *,
    seed: int = 0,
    config: SimConfig | None = None,
    controls_schedule: np.ndarray | None = None,
    workers: int = 1,
    executor: Executor = "process",
    progress: bool = True,
    on_case: Callable[[int, dict], None] | None = None,
    state_dtype: str = "float32",
    seed_ids: Sequence[int] | None = None,
    geometry: tuple[str, np.ndarray] | None = None,
) -> dict:
    """Simulate ``case_ids`` (rows of ``controls_raw``) into ``out``, resuming a compatible existing file.

    Args:
      out: HDF5 path. scene, rules: as for ``simulate_trajectory``.
      controls_raw: (N, 14) raw constant controls (for recipes: the first transition's vector).
      case_ids: (N,) ids stored with each row. seed: base seed (module docstring).
      controls_schedule: optional (N, T, 14) recipes, one control vector per transition.
      workers: parallel simulations (1 = in-process). executor: "process" or "ray".
      progress: show a tqdm bar. on_case: callback(row, meta) after each written case.
      state_dtype: "float32" or "float16" storage of the states (``nemsim.data.hdf5``; reads are float32).
      seed_ids: optional (N,) case id whose seed each row uses (default: its own case id).
      geometry: optional (kind, (N, 2) [cd_nm, mask_nm]) each case's feature (module docstring).
    Returns: {"written": int, "skipped": int, "wall_s": float, "path": str}.
    """
    from nemsim.data.hdf5 import TrajectoryWriter

    if executor not in EXECUTORS:
        raise ValueError(f"executor {executor!r} is not one of {EXECUTORS}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    config = (config or SimConfig()).resolved(scene)
    features: list[Feature | None] = [None] * len(case_ids)
    if geometry is not None:  # each row's feature as built on the grid, all checked before the file
        features = list(case_features(geometry[0], geometry[1], scene))
        if len(features) != len(case_ids):
            raise ValueError(f"{len(features)} geometry rows for {len(case_ids)} cases")
        geometry = (geometry[0], np.array([[f.cd_nm, f.mask_nm] for f in features if f is not None]))
    for feature in {f for f in features}:  # e.g. the quarter domain on an odd grid, the section on a hole
        config.check_scene(scene if feature is None else feature.apply(scene))
    controls_raw = np.asarray(controls_raw, dtype=np.float64)
    case_ids = [int(c) for c in case_ids]
    seed_of = case_ids if seed_ids is None else [int(c) for c in seed_ids]
    if len(seed_of) != len(case_ids):
        raise ValueError(f"{len(seed_of)} seed ids for {len(case_ids)} cases")
    if controls_raw.shape != (len(case_ids), 14):
        raise ValueError(f"controls_raw must be ({len(case_ids)}, 14) for {len(case_ids)} cases, got "
                         f"{controls_raw.shape}")  # fmt: skip
    with _sigterm_as_interrupt() as stop:  # a kill -TERM cleans up like Ctrl-C
        t0 = time.perf_counter()
        writer = TrajectoryWriter(
            out,
            scene=scene,
            case_ids=case_ids,
            controls_raw=controls_raw,
            generator=generator_meta(scene, config, seed),
            rules_sha256=rules.sha256,
            controls_schedule=controls_schedule,
            state_dtype=state_dtype,
            geometry=geometry,
        )
        ok = False
        results: Iterator[tuple] | None = None
        try:
            done = writer.finished
            sched = controls_schedule
            tasks = [
                CaseTask(
                    row=row, case_id=cid, seed=case_seed(seed, seed_of[row]),
                    controls=controls_raw[row] if sched is None else np.asarray(sched[row]),
                    feature=features[row],
                )  # fmt: skip
                for row, cid in enumerate(case_ids)
                if row not in done
            ]
            if done:
                log.info("%s: %d of %d cases already complete; simulating the other %d", out, len(done),
                         len(case_ids), len(tasks))  # fmt: skip
            if executor == "ray":
                results = _run_ray(scene, rules, config, tasks, workers)
            elif workers == 1 or len(tasks) <= 1:
                stop.raise_now = True
                stop.check()
                results = _run_serial(scene, rules, config, tasks)
            else:
                results = _run_process_pool(scene, rules, config, tasks, workers, stop)
            bar = None
            if progress and tasks:
                from tqdm import tqdm

                bar = tqdm(total=len(tasks), unit="case", desc=f"generate {scene.name}", dynamic_ncols=True)
            try:
                for row, states, case_sd, meta in results:
                    writer.write(row, states, seed=case_sd, meta=meta)
                    stop.check()  # after writing: a finished case is kept
                    if on_case is not None:
                        on_case(row, meta)
                    if bar is not None:
                        bar.update(1)
                        bar.set_postfix(last_s=f"{meta['wall_s']:.1f}")
            finally:
                if bar is not None:
                    bar.close()
            ok = True
        finally:
            if isinstance(results, Generator):
                results.close()  # stop the workers now (the pool's cleanup), not when it is collected
            writer.close(validate=ok)
    return {"written": len(tasks), "skipped": len(done), "wall_s": time.perf_counter() - t0, "path": str(out)}
