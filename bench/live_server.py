"""A real `nemsim serve` process on a loopback port, for the probes of `bench.service_probes`.

`LiveServer` starts the server with the default settings (every inherited `NEMSIM_*` variable removed),
its simulator-job folders in a directory of its own (`NEMSIM_JOBS_DIR`), and waits for `/ready`. The
helpers here read a process's memory from /proc, find the simulator children of a job folder, draw
random in-box controls and summarise latencies. Clients on other loopback addresses (127.0.0.2, ...) bind
their sockets there (`client(source=...)`): the server sees them as other clients.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, from_normalized
from service.job_processes import JOB_DIR_PREFIX
from service.protocol import free_port

READY_TIMEOUT_S = 300.0


class LiveServer:
    """`nemsim serve --checkpoint <checkpoint> --port <free port>` (module docstring); `env`: NEMSIM_*
    settings on top of the defaults (the probes pass none but the jobs folder)."""

    def __init__(
        self, checkpoint: str | Path, jobs_dir: Path, log_path: Path, env: dict[str, str] | None = None
    ) -> None:
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.jobs_dir = jobs_dir
        server_env = {k: v for k, v in os.environ.items() if not k.startswith("NEMSIM_")}
        server_env.update({"NEMSIM_JOBS_DIR": str(jobs_dir), **(env or {})})
        self._log = open(log_path, "ab")  # noqa: SIM115 -- closed in stop()
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "nemsim.cli",
                "serve",
                "--checkpoint",
                str(checkpoint),
                "--port",
                str(self.port),
            ],
            env=server_env,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
        )
        self.log_path = log_path

    @property
    def pid(self) -> int:
        return self.proc.pid

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> float:
        """Seconds until `/ready` answered 200; RuntimeError (with the log's tail) if the server exits or
        the time runs out."""
        t0 = time.monotonic()
        with client(self) as http:
            while True:
                try:
                    if http.get("/ready").status_code == 200:
                        return time.monotonic() - t0
                except httpx.TransportError:
                    pass
                if self.proc.poll() is not None or time.monotonic() - t0 > timeout_s:
                    tail = self.log_path.read_text(errors="replace")[-2000:]
                    raise RuntimeError(
                        f"nemsim serve did not become ready (exit {self.proc.poll()}):\n{tail}"
                    )
                time.sleep(0.2)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 60.0) -> tuple[int | None, float]:
        """Send `sig` and wait for the exit: (exit status, seconds); SIGKILL after `timeout_s`."""
        t0 = time.monotonic()
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode, time.monotonic() - t0


def client(server: LiveServer, *, source: str | None = None, timeout_s: float = 120.0) -> httpx.Client:
    """An HTTP client of `server`, its sockets bound to the loopback address `source` if given."""
    transport = httpx.HTTPTransport(local_address=source) if source else httpx.HTTPTransport()
    return httpx.Client(base_url=server.base, timeout=timeout_s, transport=transport)


def memory_mib(pid: int) -> dict[str, float]:
    """Resident (VmRSS) and peak resident (VmHWM) size of process `pid`, MiB (Linux /proc)."""
    fields = dict(
        line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line
    )
    return {k: int(fields[name].split()[0]) / 1024 for k, name in (("rss", "VmRSS"), ("peak", "VmHWM"))}


def job_children(jobs_dir: Path) -> list[int]:
    """Pids of the live simulator children (`service.sim_child`) working in a folder under `jobs_dir`."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:  # gone meanwhile
            continue
        if (
            state != "Z"
            and b"service.sim_child" in argv
            and any(a.startswith(str(jobs_dir).encode()) for a in argv)
        ):
            pids.append(int(entry.name))
    return pids


def nice_of(pid: int) -> int | None:
    """The nice value of process `pid` (its main thread; Linux /proc), None if it is gone."""
    try:
        return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[16])
    except (OSError, IndexError, ValueError):
        return None


def autogroup(pid: int) -> str | None:
    """The scheduler autogroup of process `pid` ("/autogroup-N nice K"; Linux with autogroups on, which
    weigh CPU time per session first: a process's nice counts only against its own session's), None if
    the kernel has none or the process is gone."""
    try:
        if Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() != "1":
            return None
        return Path(f"/proc/{pid}/autogroup").read_text().strip()
    except OSError:
        return None


def job_dirs(jobs_dir: Path) -> list[Path]:
    return sorted(jobs_dir.glob(JOB_DIR_PREFIX + "*"))


def wait_until(predicate: Any, timeout_s: float, poll_s: float = 0.1) -> float | None:
    """Seconds until `predicate()` held, or None if it did not within `timeout_s`."""
    t0 = time.monotonic()
    while True:
        if predicate():
            return time.monotonic() - t0
        if time.monotonic() - t0 > timeout_s:
            return None
        time.sleep(poll_s)


def random_controls(rng: np.random.Generator) -> dict[str, float]:
    """Controls drawn uniformly in the design (training) box, in physical units, exponents whole."""
    raw = np.asarray(from_normalized(rng.uniform(-1, 1, len(CONTROL_NAMES))), dtype=np.float64)  # (14,)
    for i, spec in enumerate(CONTROL_SPECS):
        if spec.kind == "int":
            raw[i] = round(raw[i])
    return dict(zip(CONTROL_NAMES, map(float, raw), strict=True))


def centre_controls() -> dict[str, float]:
    """The documented default controls (the design-range centre)."""
    from service.schemas import array_to_controls, default_controls_raw

    return dict(array_to_controls(default_controls_raw()))


def percentiles_ms(samples_s: list[float]) -> dict[str, float | int]:
    """n, p50 and p95 (ms) of latencies in seconds."""
    if not samples_s:
        return {"n": 0}
    ms = np.asarray(samples_s) * 1e3
    return {"n": int(ms.size), "p50_ms": float(np.percentile(ms, 50)), "p95_ms": float(np.percentile(ms, 95))}


def count(codes: dict[str, int], code: int | str) -> None:
    codes[str(code)] = codes.get(str(code), 0) + 1


def server_errors(codes: dict[str, int]) -> int:
    """Answers 500..599 among status counts (transport failures are counted apart)."""
    return sum(n for c, n in codes.items() if c.isdigit() and 500 <= int(c) <= 599)
