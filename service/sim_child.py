"""The simulator job's child process: ``python -m service.sim_child <job folder> <server pid>``.

`service.jobs.run_simulator` writes the inputs (`input.pkl`: scene, simulator config, (T, 14) schedule,
seed) into the job's folder and starts this in a session (process group) of its own. The child

* dies with the server: on Linux the kernel sends it SIGKILL when the server thread that started it
  ends, `kill -9` of the server included (`prctl(PR_SET_PDEATHSIG)`); where that is not available, a
  watchdog thread exits once the parent is gone. A server that died before the guard was set (the parent
  is no longer the given pid) means exit at once;
* runs at the lowest CPU priority (nice 19, its scheduler autogroup too): interactive rollouts get the
  cores first;
* writes the transitions done to `progress`, then the states (float16) to `states.npy`, or one line
  naming the failure to `error` (exit status 1).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import pickle
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

PR_SET_PDEATHSIG = 1  # linux/prctl.h
EXIT_ORPHANED = 3  # the server was gone before the simulation started
WATCHDOG_S = 1.0  # how often the portable watchdog checks the parent


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


def lowest_priority() -> None:
    """Nice 19 (POSIX); background work must never take the CPU from interactive requests.

    Linux with scheduler autogroups (the default on desktops and many servers) weighs sessions against each
    other first and applies a nice value only within its session's group; this process leads a session of
    its own, so its group's nice is set to 19 too (``/proc/self/autogroup``, sched(7))."""
    if hasattr(os, "nice"):
        with contextlib.suppress(OSError):  # a sandbox that forbids it: run as is
            os.nice(19)  # clamped at 19
    autogroup = Path("/proc/self/autogroup")
    if autogroup.exists():
        with contextlib.suppress(OSError):
            autogroup.write_text("19")


def simulate(job_dir: Path) -> None:
    """Run the simulation described by `job_dir/input.pkl`; progress and states into `job_dir`."""
    from nemsim.rules.compile import compile_rules
    from nemsim.rules.schema import load_rules
    from nemsim.sim import run_trajectory

    # written by the server that started this process, into a folder only its user can write
    scene, config, schedule, seed = pickle.loads((job_dir / "input.pkl").read_bytes())
    progress = job_dir / "progress"

    def report(k: int, _total: int) -> None:
        progress.write_text(str(k))

    rules = compile_rules(load_rules())
    # the simulator takes a full-horizon recipe; transitions past `steps` are never run
    full = np.concatenate([schedule, np.repeat(schedule[-1:], scene.n_transitions - len(schedule), 0)])
    res = run_trajectory(
        scene, rules, full, np.random.default_rng(seed), config,
        n_transitions=len(schedule), on_transition=report,
    )  # fmt: skip
    tmp = job_dir / "states.partial.npy"
    np.save(tmp, res.states.astype(np.float16))
    os.replace(tmp, job_dir / "states.npy")


def main(argv: list[str]) -> int:
    job_dir, server_pid = Path(argv[0]), int(argv[1])
    die_with_parent(server_pid)
    lowest_priority()
    try:
        simulate(job_dir)
    except Exception as exc:  # noqa: BLE001 -- the server reports it on the job
        (job_dir / "error").write_text(f"{type(exc).__name__}: {exc}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
