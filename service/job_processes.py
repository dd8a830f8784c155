"""The jobs' child processes, server side (the child's side: `service.sim_child`): simulator runs and
inverse designs alike.

Nothing outlives the server: each child runs in a session (process group) of its own and is killed, group
and all, with its folder removed, when its job ends or is cancelled (`SimulatorChildren.finish`) or the
server stops (`kill_all`: lifespan shutdown; `kill_all_children`: SIGTERM / SIGINT through
`stop_children_on_signals`, which runs before the server's own handlers, and interpreter exit). The kernel
kills a child whose server died without any of these (`kill -9`; see `service.sim_child`). Each child's
files live in a `nemsim-job-*` folder holding an `owner` file (the server's pid and start time, since a
pid alone may be reused); `remove_orphaned_dirs` removes, at start-up, the folders whose owner is gone.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from pathlib import Path
from typing import Any

JOB_DIR_PREFIX = "nemsim-job-"  # one folder per job child under the queue's work_dir
OWNER_FILE = "owner"  # in each job folder: "<server pid> <its start time>"
ORPHAN_GRACE_S = 60.0  # a job folder without an owner file this old was left by a crash while created


class ChildrenStopped(Exception):
    """The server is stopping: no new job child is started."""


def process_start(pid: int) -> str:
    """When process `pid` started, in clock ticks since boot (Linux; "" elsewhere or when unknown): a pid
    alone may have been reused by another process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return ""
    return stat.rsplit(")", 1)[-1].split()[19]  # field 22; the name before ")" may hold spaces


def owner_alive(token: str) -> bool:
    """Whether the process named by an owner token ("<pid> <start>") is still running."""
    pid_text, _, start = token.strip().partition(" ")
    try:
        pid = int(pid_text)
        os.kill(pid, 0)
    except (ValueError, OverflowError, ProcessLookupError):
        return False
    except PermissionError:  # alive, another user's
        return True
    return not start or process_start(pid) in ("", start)


def remove_orphaned_dirs(root: Path) -> list[Path]:
    """Remove the job folders under `root` whose owning server is gone (and those left without an owner
    file for ORPHAN_GRACE_S). Returns them."""
    removed = []
    for path in root.glob(JOB_DIR_PREFIX + "*"):
        if path.is_symlink() or not path.is_dir():
            continue
        try:
            alive = owner_alive((path / OWNER_FILE).read_text())
        except FileNotFoundError:
            try:
                alive = time.time() - path.stat().st_mtime < ORPHAN_GRACE_S
            except OSError:  # removed meanwhile
                continue
        except OSError:  # e.g. another user's folder: not ours to judge
            continue
        if not alive:
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


class SimulatorChildren:
    """The running job children (simulator runs, designs) of one job queue and the folder (`root`) their
    files go in.

    `start` runs a child in a new session (its own process group); `finish` kills the group if it still
    runs and removes the job's folder; `kill_all` does that for every child and refuses new ones
    (shutdown)."""

    def __init__(self, root: Path | None = None) -> None:
        self.root = Path(root) if root is not None else Path(tempfile.gettempdir())
        self.stopped = False
        self._running: dict[int, tuple[subprocess.Popen[bytes], Path]] = {}  # pid -> (child, folder)
        self._lock = threading.RLock()  # re-entered by a signal handler on the thread holding it
        _track(self)

    def make_dir(self) -> Path:
        """A fresh job folder (owner file written) under `root`."""
        self.root.mkdir(parents=True, exist_ok=True)
        path = Path(tempfile.mkdtemp(prefix=JOB_DIR_PREFIX, dir=self.root))
        (path / OWNER_FILE).write_text(f"{os.getpid()} {process_start(os.getpid())}")
        return path

    def start(self, job_dir: Path, task: str = "simulate") -> subprocess.Popen[bytes]:
        """Run `task` of `service.sim_child` on `job_dir` (ChildrenStopped once `kill_all` ran)."""
        env = dict(os.environ)
        for var in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env.setdefault(var, "1")  # one core per job
        package_root = str(Path(__file__).resolve().parents[1])  # `service` importable from any cwd
        env["PYTHONPATH"] = os.pathsep.join(p for p in (package_root, env.get("PYTHONPATH")) if p)
        argv = [sys.executable, "-m", "service.sim_child", str(job_dir), str(os.getpid()), task]
        with self._lock:
            if self.stopped:
                raise ChildrenStopped
            child = subprocess.Popen(
                argv, env=env, start_new_session=True, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL
            )
            self._running[child.pid] = (child, job_dir)
        return child

    def finish(self, child: subprocess.Popen[bytes] | None, job_dir: Path) -> None:
        """Kill `child`'s process group if it still runs and remove `job_dir`."""
        with self._lock:
            if child is not None:
                self._running.pop(child.pid, None)
        if child is not None:
            _kill_group(child)
        shutil.rmtree(job_dir, ignore_errors=True)

    def kill_all(self) -> None:
        """`finish` every running child; start no more (the server is stopping)."""
        with self._lock:
            self.stopped = True
            running, self._running = list(self._running.values()), {}
        for child, job_dir in running:
            self.finish(child, job_dir)


def _kill_group(child: subprocess.Popen[bytes]) -> None:
    if child.returncode is None:  # not reaped: its pid (the group's id) cannot have been reused
        with contextlib.suppress(ProcessLookupError, PermissionError):
            if hasattr(os, "killpg"):
                os.killpg(child.pid, signal.SIGKILL)
            else:  # no process groups (Windows): the child alone
                child.kill()
    with contextlib.suppress(subprocess.TimeoutExpired):
        child.wait(5)


# every queue's children, for the process-wide exits (signals, interpreter exit): weak, so a closed queue
# that nobody holds is forgotten
_ALL_CHILDREN: weakref.WeakSet[SimulatorChildren] = weakref.WeakSet()
_HOOKS = {"atexit": False}


def _track(children: SimulatorChildren) -> None:
    _ALL_CHILDREN.add(children)
    if not _HOOKS["atexit"]:
        _HOOKS["atexit"] = True
        atexit.register(kill_all_children)


def kill_all_children() -> None:
    """Kill every job child of this process and remove their folders."""
    for children in list(_ALL_CHILDREN):
        children.kill_all()


def stop_children_on_signals(signals: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)) -> None:
    """Put `kill_all_children` in front of the current handlers of `signals` (which still run next: the
    server's graceful shutdown). Only the main thread may set handlers; elsewhere (an app run in a test
    client's thread) nothing happens and shutdown and exit still stop the children."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in signals:
        previous = signal.getsignal(sig)
        if getattr(previous, "kills_simulator_children", False):
            continue

        def handler(signum: int, frame: Any, previous: Any = previous) -> None:
            kill_all_children()
            if callable(previous):
                previous(signum, frame)
            elif previous == signal.SIG_DFL:
                signal.signal(signum, signal.SIG_DFL)
                signal.raise_signal(signum)

        handler.kills_simulator_children = True  # type: ignore[attr-defined]
        signal.signal(sig, handler)
