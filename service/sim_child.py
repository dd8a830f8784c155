"""The job children's process: ``python -m service.sim_child <job folder> <server pid> [<task>]``.

Every job's heavy work runs here, never in the server process: a simulator run (task `simulate`, the
default: `service.jobs.run_simulator`) or an inverse design (task `design`: `service.inverse.design_work`
on the server's side, `design_in_child` here). `service.jobs.run_child` writes the task's
inputs (`input.pkl`, and whatever else the task reads) into the job's folder and starts this in a session
(process group) of its own. The child

* dies with the server: on Linux the kernel sends it SIGKILL when the server thread that started it
  ends, `kill -9` of the server included (`prctl(PR_SET_PDEATHSIG)`); where that is not available, a
  watchdog thread exits once the parent is gone. A server that died before the guard was set (the parent
  is no longer the given pid) means exit at once;
* runs at `JOB_NICE`, the server's CPU priority (its scheduler autogroup too): never starved, and one
  job at a time takes at most one core (`job_priority`);
* writes the share of its work done (a number in [0, 1]) and, on a second line, what it is doing (a
  design: loading the model, screening, the search's steps, simulator run k of n) to `progress`, its
  output into the folder (the
  simulator: `states.npy`; a design: `result.json`), or its failure to `error` (exit status 1): JSON
  ``{"type": exception class name, "message": its text}``.

Choices: one entry point for every kind of job (the process management, the exits and the orphan checks
are the same for all, and the server finds its children by this module's name); a design's own simulator
runs (verification, simulator-corrected rounds) run inside its child, as `nemsim inverse` runs them in
its one process: cancelling the job kills them with it.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import pickle
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

PR_SET_PDEATHSIG = 1  # linux/prctl.h
EXIT_ORPHANED = 3  # the server was gone before the work started
WATCHDOG_S = 1.0  # how often the portable watchdog checks the parent
INPUT_FILE, PROGRESS_FILE, ERROR_FILE = "input.pkl", "progress", "error"
TASKS = ("simulate", "design")
CONFIRM_SEED_OFFSET = 1  # a refined design's confirmation runs with the design's simulator seed + this
SEARCH_SHARE = 0.6  # progress share of a design's search when the job also verifies
MODEL_FILE, RESULT_FILE = "model.pt", "result.json"  # in a design job's folder
JOB_NICE = 0  # job children and job worker threads: this much nicer than the server (`job_priority`)


def die_with_parent(server_pid: int) -> None:
    """Make the kernel kill this process when its parent dies (Linux), else watch the parent from a
    thread; exit at once if the parent is already gone."""
    guarded = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            guarded = libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):  # no usable libc: the watchdog below does it
            guarded = False
    if os.getppid() != server_pid:
        os._exit(EXIT_ORPHANED)
    if not guarded:

        def watch() -> None:
            while os.getppid() == server_pid:
                time.sleep(WATCHDOG_S)
            os._exit(EXIT_ORPHANED)

        threading.Thread(target=watch, name="nemsim-parent-watch", daemon=True).start()


def job_priority() -> None:
    """`JOB_NICE` nicer than the server (POSIX), the job's scheduler autogroup too.

    A core shared with one other busy process is split by the kernel's weights per nice level (sched(7)):
    at nice 0 half each, so a job goes at least half its quiet pace beside any one CPU-bound process; at
    nice 2 it would get 39 %, at nice 19 1.5 % (a starved job whose progress stands still). Interactive
    rollouts are protected by numbers instead: one job runs at a time on one thread
    (`NEMSIM_SIM_WORKERS`), so a job takes at most one core from the server.

    Linux with scheduler autogroups (the default on desktops and many servers) weighs sessions against each
    other first and applies a nice value only within its session's group; this process leads a session of
    its own, so its group's nice is set to `JOB_NICE` too (``/proc/self/autogroup``, sched(7))."""
    if hasattr(os, "nice"):
        with contextlib.suppress(OSError):  # a sandbox that forbids it: run as is
            os.nice(JOB_NICE)
    autogroup = Path("/proc/self/autogroup")
    if autogroup.exists():
        with contextlib.suppress(OSError):
            autogroup.write_text(str(JOB_NICE))


def write_atomically(path: Path, data: bytes) -> None:
    """Write `path` so that a reader sees the old content or the new, never a part of it."""
    tmp = path.with_name(path.name + ".partial")
    tmp.write_bytes(data)
    os.replace(tmp, path)


class Report(Protocol):
    """report(share, phase): the share of a task's work done (0..1; None: as before) and what it is doing
    (None: as before)."""

    def __call__(self, share: float | None, phase: str | None = None) -> None: ...


def progress_writer(job_dir: Path) -> Report:
    """A task's `Report`: "<share>\n<phase>" written to `progress` when either moved."""
    last: list[Any] = [0.0, ""]

    def report(share: float | None, phase: str | None = None) -> None:
        now = [last[0] if share is None else round(min(max(float(share), 0.0), 1.0), 4),
               last[1] if phase is None else phase]
        if now != last:
            last[:] = now
            write_atomically(job_dir / PROGRESS_FILE, f"{now[0]}\n{now[1]}".encode())

    return report


_RULES: list[Any] = []  # the compiled default rules library, once per process


def simulate_schedule(
    scene: Any, config: Any, schedule: np.ndarray, seed: int, report: Callable[[float], None]
) -> np.ndarray:
    """The simulator on (T, 14) `schedule`: (T+1, 2, D, H, W) float16 states; report(share of T done)."""
    from nemsim.sim import run_trajectory

    if not _RULES:
        from nemsim.rules.compile import compile_rules
        from nemsim.rules.schema import load_rules

        _RULES.append(compile_rules(load_rules()))
    steps = len(schedule)
    # the simulator takes a full-horizon recipe; transitions past `steps` are never run
    full = np.concatenate([schedule, np.repeat(schedule[-1:], scene.n_transitions - steps, 0)])
    res = run_trajectory(
        scene, _RULES[0], full, np.random.default_rng(seed), config,
        n_transitions=steps, on_transition=lambda k, _total: report(k / steps),
    )  # fmt: skip
    return res.states.astype(np.float16)


def simulate_task(job_dir: Path, inputs: Any, report: Report) -> None:
    """Task `simulate`: inputs (scene, simulator config, (T, 14) schedule, seed); states to `states.npy`."""
    scene, config, schedule, seed = inputs
    states = simulate_schedule(scene, config, schedule, seed, report)
    tmp = job_dir / "states.partial.npy"
    np.save(tmp, states)
    os.replace(tmp, job_dir / "states.npy")


def design_in_child(job_dir: Path, inputs: dict[str, Any], report: Report) -> None:
    """Task `design`: load the weights `service.inverse.design_work` wrote, run the design, write
    `result.json`. The design's simulator runs are this process's (`simulate_schedule`, what a simulator
    job's child runs)."""
    report(0.0, "loading the model")
    import torch

    from nemsim.analysis.intervals import Support
    from nemsim.analysis.inverse import InverseContext
    from nemsim.inference.checkpoint import load_checkpoint

    torch.set_num_threads(int(inputs["threads"]))
    loaded = load_checkpoint(job_dir / MODEL_FILE)
    cal = inputs["calibration"]
    ctx = InverseContext(
        model=loaded.model,
        scene=inputs.get("scene") or loaded.scene,  # the feature's per-case scene (service.inverse)
        x0=torch.from_numpy(inputs["x0"]),
        calibration=cal,
        support=Support.from_record(cal.support if cal else None),
        model_id=inputs["model_id"],
        loaded=loaded,
    )
    result = _design(ctx, inputs, report)
    write_atomically(job_dir / RESULT_FILE, json.dumps(result, default=_plain).encode())


def _plain(value: Any) -> Any:
    """numpy scalars and arrays as Python numbers and lists (json.dumps' `default`)."""
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def _design(ctx: Any, o: dict[str, Any], report: Report) -> dict[str, Any]:
    """The design of `service.inverse.design_work` (its options in `o`), its recipes labelled predicted or
    simulated (`label_recipes`); report(share of the job done, phase): the search's stages, then
    "simulator run k of n" (of at most n for a simulator-corrected design) with its steps."""
    from nemsim.analysis.inverse import (
        SimulationSkipped,
        label_recipes,
        refine_with_simulator,
        search,
        simulated_metrics,
        verify_recipes,
    )
    from nemsim.controls import CONTROL_NAMES
    from nemsim.evaluation.truth import particle_work

    spec = o["spec"]
    sim_max_work = o["sim_max_work"]
    runs = [0]  # simulator runs started

    def simulated(raw: np.ndarray, steps: int, share: Callable[[float], float | None], planned: str,
                  seed: int | None = None) -> np.ndarray:
        schedule = np.repeat(raw[None], steps, axis=0)  # (T, 14)
        seed = o["sim_seed"] if seed is None else seed
        runs[0] += 1
        label = f"simulator run {runs[0]} of {planned}"

        def progress(f: float) -> None:
            report(share(f), f"{label}: step {round(f * steps)}/{steps}")

        progress(0.0)
        try:
            states = simulate_schedule(ctx.scene, o["sim_config"], schedule, seed, progress)
        except Exception as exc:  # noqa: BLE001 -- named as a simulator job's failure is
            raise RuntimeError(f"the simulator failed: {type(exc).__name__}: {exc}") from exc
        return states.astype(np.float32)  # float16 states, as a simulator job's

    if o["refine"] is not None:

        def simulator(seed: int) -> Callable[[np.ndarray, int], np.ndarray]:
            def simulate(raw: np.ndarray, steps: int) -> np.ndarray:
                work = particle_work([(raw, 0)])
                if work > sim_max_work:
                    raise SimulationSkipped(
                        f"{work:.3g}x the work of a design-centre run (server limit {sim_max_work:g}x)"
                    )
                # the share stands still meanwhile: the loop decides how many runs it makes
                return simulated(raw, steps, lambda _f: None, f"at most {o['refine'].max_runs}", seed)

            return simulate

        # a recipe met in its loop run is confirmed by an independent run (the next seed) before it is the
        # answer: the strategy `nemsim bench design-cost` measures as "design"
        return label_recipes(refine_with_simulator(
            ctx,
            spec,
            simulated_metrics(simulator(o["sim_seed"]), ctx.scene),
            refine=o["refine"],
            seed=o["seed"],
            sim_seed=o["sim_seed"],
            on_progress=lambda f, msg: report(0.98 * f, msg),
            confirm=simulated_metrics(simulator(o["sim_seed"] + CONFIRM_SEED_OFFSET), ctx.scene),
        ), spec)
    share = SEARCH_SHARE if o["verify"] else 0.98
    result = search(ctx, spec, seed=o["seed"], on_progress=lambda f, msg: report(share * f, msg))
    if o["verify"]:
        top = min(o["verify_top"], len(result["recipes"]))
        span = (0.98 - share) / max(top, 1)
        skipped = []
        for i, rec in enumerate(result["recipes"][:top]):
            raw = np.array([rec["controls"][n] for n in CONTROL_NAMES], dtype=np.float64)
            work = particle_work([(raw, 0)])
            if work > sim_max_work:
                skipped.append(
                    f"recipe {i + 1}: {work:.3g}x the work of a design-centre run (server limit "
                    f"{sim_max_work:g}x)"
                )
        def simulate_top(raw: np.ndarray, steps: int) -> np.ndarray:
            base = share + span * runs[0]
            return simulated(raw, steps, lambda f: base + span * f, str(top))

        if skipped:
            result["verification"] = {"seed": o["sim_seed"], "recipes": [], "skipped": skipped}
        else:
            result["verification"] = {
                "seed": o["sim_seed"],
                "recipes": verify_recipes(result, spec, ctx.scene, simulate_top, top),
            }
    return label_recipes(result, spec)


def task_function(task: str) -> Callable[[Path, Any, Report], None]:
    """The function of `task` (TASKS): fn(job folder, inputs, report(share of the work done, 0..1))."""
    if task == "simulate":
        return simulate_task
    if task == "design":
        return design_in_child
    raise ValueError(f"unknown task {task!r}; expected one of {TASKS}")


def run_task(job_dir: Path, task: str) -> None:
    """Run `task` on `job_dir`'s inputs."""
    fn = task_function(task)
    # written by the server that started this process, into a folder only its user can write
    inputs = pickle.loads((job_dir / INPUT_FILE).read_bytes())
    fn(job_dir, inputs, progress_writer(job_dir))


def main(argv: list[str]) -> int:
    job_dir, server_pid = Path(argv[0]), int(argv[1])
    task = argv[2] if len(argv) > 2 else "simulate"
    die_with_parent(server_pid)
    job_priority()
    try:
        run_task(job_dir, task)
    except Exception as exc:  # noqa: BLE001 -- the server reports it on the job
        error = {"type": type(exc).__name__, "message": str(exc)}
        (job_dir / ERROR_FILE).write_text(json.dumps(error))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
