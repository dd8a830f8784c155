"""Run what a comparison plan has left: `nemsim train` subprocesses, one core each, resumable.

Each startable entry (partial ones first, then pending ones in plan order; a blocked one as soon as the runs
it waits for are done) runs as::

    [taskset -c CORE] python -m nemsim.cli train --model M --data D --setting S --splits SP \\
        --config RUN/config.yaml --out RUN --resume --no-progress [--no-test: probes]

with OMP_NUM_THREADS=1 (one thread on its own core: the comparison's equal footing) and the `nemsim`
command's tuned allocator. Its output goes to RUN/console.log; `nemsim train` writes its own log to
RUN/train.log. At most ``jobs`` run at once, each pinned to the least used of ``cores`` when taskset exists.
The merged config is written into RUN when the run starts; a later start refuses a different one (a resumed
run must keep the learning rate and size it was measured with).

Why a subprocess per run: a run is then exactly the documented `nemsim train` command, killed and resumed
like one. The children stay in the runner's process group, so Ctrl-C or a kill of the group reaches them too;
SIGINT or SIGTERM to the runner alone stops them (SIGINT, SIGKILL after a grace period). Each keeps the
last.pt it wrote every ``checkpoint_every`` steps and the same command resumes it. One runner at a time per
runs dir (a lock file), so two never train the same run. A finished run's small files go
into the plan's record (``plan.record_run``), to be committed. ``hours`` bounds the runner's own time: a run
is started only if its remaining budget and a margin for start-up and test fit in the time left, because a
run cut off on a machine that does not survive is lost.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.comparison.plan import (
    Plan,
    PlanError,
    RunStatus,
    config_text,
    format_status,
    measure,
    plan_status,
    record_run,
    run_config,
    run_dir,
)

MARGIN_MIN = {True: 2.0, False: 15.0}  # probe / full: start-up, last validation and test beyond the budget
GRACE_S = 20.0  # after SIGINT, seconds a child has to exit before SIGKILL
LOCK = ".compare.lock"  # in the runs dir, held while a runner works there

Echo = Callable[[str], Any]


@dataclass(frozen=True)
class RunnerConfig:
    runs_dir: Path = Path("runs/compare-45min")  # scratch run directories (not committed)
    jobs: int = 1  # runs at once
    cores: tuple[int, ...] = (0, 1)  # CPU cores the runs are pinned to (taskset), one run per core first
    only: tuple[str, ...] = ()  # entry names to run; empty: all
    hours: float | None = None  # start nothing that would not finish within this many hours
    dry_run: bool = False  # print what would run, write nothing
    poll_s: float = 1.0  # seconds between checks of the running children
    python: str = sys.executable  # the interpreter of the children


class _Terminated(Exception):
    """SIGTERM, raised in the main thread so the children are stopped as on Ctrl-C."""


@dataclass
class _Child:
    status: RunStatus
    proc: subprocess.Popen
    core: int | None
    log: Path
    t0: float


def _default_signals() -> None:
    """In the child before exec: SIGINT and SIGTERM back to their defaults. A signal the runner's process
    ignores would otherwise stay ignored in the child (exec keeps SIG_IGN), and the SIGINT of ``_stop``
    would not stop it (seen when a caller in the same process had set SIGINT to SIG_IGN)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def check_data(plan: Plan) -> None:
    """Refuse to run without the plan's data file and splits, naming the commands that make them."""
    for path in (plan.data, plan.splits):
        if not path.exists():
            how = " then ".join(f"`{c}`" for c in plan.make_data) or "the plan's make_data commands"
            raise PlanError(f"{path} does not exist: make it with {how}")


def train_command(plan: Plan, status: RunStatus, cfg: RunnerConfig, core: int | None) -> list[str]:
    entry, choice = status.entry, status.choice
    out = run_dir(cfg.runs_dir, entry, choice)
    assert choice is not None and out is not None, f"{entry.name} is not startable"
    cmd = [cfg.python, "-m", "nemsim.cli", "train", "--model", choice.model, "--data", str(plan.data),
           "--setting", entry.setting, "--splits", str(plan.splits), "--config", str(out / "config.yaml"),
           "--out", str(out), "--resume", "--no-progress"]  # fmt: skip
    if entry.probe:
        cmd.append("--no-test")
    taskset = shutil.which("taskset")
    return [taskset, "-c", str(core), *cmd] if taskset and core is not None else cmd


def _environment() -> dict[str, str]:
    from nemsim.cli.allocator import tuned_environ

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return tuned_environ(env) or env


def config_changes(stored: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """The keys where a started run's stored configuration and the plan's now differ. A training key the
    stored file lacks counts as its default (a field added to ``TrainConfig`` after the run started, with a
    default that keeps the old behaviour, does not change the run)."""
    from dataclasses import asdict

    from nemsim.training.config import TrainConfig

    defaults = json.loads(json.dumps(asdict(TrainConfig())))
    stored = {**{k: v for k, v in defaults.items() if k in now}, **stored}
    return sorted(k for k in {*stored, *now} if stored.get(k) != now.get(k))


def _write_config(plan: Plan, status: RunStatus, out: Path) -> None:
    """RUN/config.yaml: written for a fresh run; for a started one it must match what the plan gives now."""
    import yaml

    assert status.choice is not None
    path = out / "config.yaml"
    started = (out / "last.pt").is_file() or (out / "summary.json").is_file()
    if started and path.is_file():
        keys = config_changes(yaml.safe_load(path.read_text()), run_config(plan, status.entry, status.choice))
        if keys:
            raise PlanError(f"{path}: the run started with other {keys} than the plan gives now; "
                            f"remove {out} to start it over, or restore the plan")  # fmt: skip
        return
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(config_text(plan, status.entry, status.choice))


def _core(cfg: RunnerConfig, running: dict[str, _Child]) -> int:
    use = {c: sum(ch.core == c for ch in running.values()) for c in cfg.cores}
    return min(cfg.cores, key=lambda c: use[c])


def _say(echo: Echo, text: str) -> None:
    echo(f"[{time.strftime('%H:%M:%S')}] {text}")


def _start(plan: Plan, status: RunStatus, cfg: RunnerConfig, running: dict[str, _Child],
           echo: Echo) -> _Child:
    out = run_dir(cfg.runs_dir, status.entry, status.choice)
    assert out is not None and status.choice is not None
    _write_config(plan, status, out)
    core = _core(cfg, running)
    cmd = train_command(plan, status, cfg, core)
    log = out / "console.log"
    with log.open("ab") as fh:  # the child keeps its own descriptor
        fh.write(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} nemsim bench compare: {' '.join(cmd)}\n".encode())
        fh.flush()
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, env=_environment(),
                                preexec_fn=_default_signals)
    c, e = status.choice, status.entry
    lr = "recipe lr" if c.lr is None else f"lr {c.lr:g}"
    spent = f"{status.spent_min:.1f}" if status.spent_min is not None else "0"
    pinned = f"core {core}" if cmd[0] != cfg.python else "not pinned (no taskset)"
    _say(echo, f"start {e.name}: {c.model} ({c.size}, {lr}) on {e.setting}, {spent} of {e.minutes:g} min "
               f"spent; {pinned}; log {log}")
    return _Child(status, proc, core, log, time.monotonic())


def _last_line(path: Path) -> str:
    text = path.read_text(errors="replace") if path.is_file() else ""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    return lines[-1].strip() if lines else "no output"


def _finish(plan: Plan, child: _Child, cfg: RunnerConfig, echo: Echo) -> bool:
    """Report an ended child, record it if done; whether it failed."""
    entry, choice = child.status.entry, child.status.choice
    assert choice is not None
    st = measure(entry, choice, cfg.runs_dir, plan.record)
    wall = (time.monotonic() - child.t0) / 60
    if child.proc.returncode == 0 and st.state == "done":
        kept = record_run(st, cfg.runs_dir, plan.record)
        best = "-" if st.best_val is None else f"{st.best_val:.5f}"
        _say(echo, f"end {entry.name}: done, {st.spent_min or 0:.1f} of {entry.minutes:g} min spent "
                   f"({wall:.1f} min in this process), best val Avg RMSE {best}; "
                   f"recorded in {kept or 'the record'}")
        return False
    _say(echo, f"end {entry.name}: FAILED (exit {child.proc.returncode}) after {wall:.1f} min: "
               f"{_last_line(child.log)} (see {child.log})")
    return True


def _stop(running: dict[str, _Child], echo: Echo) -> None:
    """SIGINT to every child still running a second after the interruption (Ctrl-C reached them already),
    SIGKILL to those alive after GRACE_S or on a second interruption."""
    try:
        end = time.monotonic() + 1.0
        while time.monotonic() < end and any(ch.proc.poll() is None for ch in running.values()):
            time.sleep(0.05)
        for ch in running.values():
            if ch.proc.poll() is None:
                ch.proc.send_signal(signal.SIGINT)
        end = time.monotonic() + GRACE_S
        for ch in running.values():
            try:
                ch.proc.wait(max(0.0, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                ch.proc.kill()
    except (KeyboardInterrupt, _Terminated):
        for ch in running.values():
            ch.proc.kill()
    for name, ch in running.items():
        ch.proc.wait()
        _say(echo, f"stopped {name}: its last.pt is kept; rerun the same command to resume it")


@contextmanager
def _locked(runs_dir: Path) -> Iterator[None]:
    """Hold RUNS_DIR/LOCK; PlanError if another runner holds it."""
    import fcntl

    runs_dir.mkdir(parents=True, exist_ok=True)
    with (runs_dir / LOCK).open("w") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise PlanError(f"another `nemsim bench compare` is running in {runs_dir}") from None
        yield


def _startable(statuses: list[RunStatus], cfg: RunnerConfig, skip: set[str]) -> list[RunStatus]:
    """Partial entries first, then pending ones, each in plan order; not those in ``skip``."""
    ok = [s for s in statuses if s.state in ("partial", "pending") and s.entry.name not in skip
          and (not cfg.only or s.entry.name in cfg.only)]  # fmt: skip
    return sorted(ok, key=lambda s: s.state != "partial")


def _minutes_left(status: RunStatus) -> float:
    """Wall minutes a run still needs: its budget left plus the margin for start-up and test."""
    return max(status.entry.minutes - (status.spent_min or 0.0) + MARGIN_MIN[status.entry.probe], 0.0)


def _fits(status: RunStatus, deadline: float | None) -> bool:
    return deadline is None or time.monotonic() + 60 * _minutes_left(status) <= deadline


def _record_done(plan: Plan, statuses: list[RunStatus], cfg: RunnerConfig, echo: Echo) -> None:
    for s in statuses:
        kept = record_run(s, cfg.runs_dir, plan.record)
        if kept is not None:
            _say(echo, f"recorded {s.entry.name} in {kept}")


def _dry_run(plan: Plan, statuses: list[RunStatus], cfg: RunnerConfig, echo: Echo) -> None:
    for path in (plan.data, plan.splits):
        if not path.exists():
            echo(f"(missing: {path}; a real run refuses until it exists)")
    # the schedule a real run would follow for what can start now: --jobs slots, each run on the slot free
    # first, nothing started that would not finish within --hours (blocked runs start later, as they unblock)
    free = [0.0] * cfg.jobs  # minutes from now at which each slot is free
    limit = None if cfg.hours is None else 60.0 * cfg.hours
    for s in _startable(statuses, cfg, set()):
        slot = min(range(cfg.jobs), key=free.__getitem__)
        if limit is not None and free[slot] + _minutes_left(s) > limit:
            echo(f"would not start {s.entry.name}: it would not finish within --hours")
            continue
        cmd = train_command(plan, s, cfg, cfg.cores[slot % len(cfg.cores)])
        echo(f"would run {s.entry.name} at +{free[slot]:.0f} min: OMP_NUM_THREADS=1 {' '.join(cmd)}")
        free[slot] += _minutes_left(s)
    echo(format_status(statuses))


def run_plan(plan: Plan, cfg: RunnerConfig, echo: Echo = print) -> int:
    """Run every startable entry, at most ``cfg.jobs`` at a time, until none is left (blocked ones start as
    their dependencies finish); print the status table at the end. Returns the number of failed runs.

    Raises PlanError for bad options, missing data or another runner in the runs dir, KeyboardInterrupt after
    stopping the children on SIGINT / SIGTERM.
    """
    if cfg.jobs < 1 or not cfg.cores:
        raise PlanError(f"--jobs must be >= 1 and --cores non-empty, got {cfg.jobs} and {cfg.cores}")
    for name in cfg.only:
        plan.entry(name)
    if cfg.dry_run:
        _dry_run(plan, plan_status(plan, cfg.runs_dir), cfg, echo)
        return 0
    check_data(plan)
    main_thread = threading.current_thread() is threading.main_thread()
    with _locked(cfg.runs_dir):
        previous = signal.signal(signal.SIGTERM, _raise_terminated) if main_thread else None
        try:
            failed = _run_all(plan, cfg, echo)
        finally:
            if main_thread:
                signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
    echo(format_status(plan_status(plan, cfg.runs_dir)))
    return len(failed)


def _run_all(plan: Plan, cfg: RunnerConfig, echo: Echo) -> set[str]:
    """The loop of ``run_plan``: start what fits in the free slots, wait for a child to end, repeat.
    Returns the names of the failed runs."""
    deadline = None if cfg.hours is None else time.monotonic() + 3600 * cfg.hours
    running: dict[str, _Child] = {}
    failed: set[str] = set()
    skipped: set[str] = set()
    try:
        statuses = plan_status(plan, cfg.runs_dir)
        _record_done(plan, statuses, cfg, echo)
        while True:
            for s in _startable(statuses, cfg, failed | skipped | set(running)):
                if len(running) >= cfg.jobs:
                    break
                if not _fits(s, deadline):
                    skipped.add(s.entry.name)
                    _say(echo, f"not starting {s.entry.name}: it would not finish within --hours")
                    continue
                try:
                    running[s.entry.name] = _start(plan, s, cfg, running, echo)
                except PlanError as exc:
                    failed.add(s.entry.name)
                    _say(echo, f"not starting {s.entry.name}: {exc}")
            if not running:
                return failed
            for name in _wait_any(running, cfg.poll_s):
                if _finish(plan, running.pop(name), cfg, echo):
                    failed.add(name)
            statuses = plan_status(plan, cfg.runs_dir)
    except (KeyboardInterrupt, _Terminated):
        _stop(running, echo)
        echo(format_status(plan_status(plan, cfg.runs_dir)))
        raise KeyboardInterrupt from None


def _raise_terminated(signum: int, frame: Any) -> None:
    raise _Terminated()


def _wait_any(running: dict[str, _Child], poll_s: float) -> list[str]:
    """Names of the children that have ended, waiting until at least one has."""
    while True:
        ended = [name for name, ch in running.items() if ch.proc.poll() is not None]
        if ended:
            return ended
        time.sleep(poll_s)
