"""`nemsim serve` start-up errors and stops, on real processes bound to free loopback ports.

A bad setting is one line naming each bad variable, its value and what it accepts (exit 2, before any
loading); a directory as the checkpoint says so; an address that cannot be bound exits 4 (not the model's
3) before the model loads; SIGTERM and SIGINT drain and exit 0, also while the model warms up (no abort).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from bench.live_server import LiveServer, client
from service.cli import EXIT_BIND, EXIT_MODEL
from service.protocol import free_port

TIMEOUT_S = 120  # a start-up error comes in seconds; this bounds a server that wrongly keeps running


def serve(checkpoint: Path, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """`nemsim serve --checkpoint <checkpoint> <args>` with only `env` as NEMSIM_* settings."""
    base = {k: v for k, v in os.environ.items() if not k.startswith("NEMSIM_")}
    return subprocess.run(
        [sys.executable, "-m", "nemsim.cli", "serve", "--checkpoint", str(checkpoint), *args],
        env={**base, "OMP_NUM_THREADS": "1", **(env or {})},
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )


def test_every_bad_setting_is_named_in_one_line(tiny_checkpoint):
    bad = {
        "NEMSIM_MAX_STEPS": "abc",
        "NEMSIM_TRUSTED_PROXIES": "garbage",
        "NEMSIM_DOCS": "maybe",
        "NEMSIM_SCENE": "../etc",
        "NEMSIM_EXTRAPOLATION": "sometimes",
    }
    proc = serve(tiny_checkpoint, "--port", str(free_port()), env=bad)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nemsim serve: invalid settings: "), proc.stderr
    for expected in (
        "NEMSIM_MAX_STEPS='abc': expected an integer in 1..10000",
        "NEMSIM_TRUSTED_PROXIES='garbage': 'garbage' is not an IP address or network",
        "NEMSIM_DOCS='maybe': expected true or false",
        "NEMSIM_SCENE='../etc': expected text matching",
        "NEMSIM_EXTRAPOLATION='sometimes': expected one of 'allow', 'clip', 'refuse'",
    ):
        assert expected in lines[0], (expected, lines[0])


def test_a_directory_as_checkpoint_is_named_as_one(tiny_checkpoint):
    proc = serve(tiny_checkpoint.parent, "--port", str(free_port()))
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "is a directory: name a .pt file (it holds tiny_nemsim.pt)" in proc.stderr
    assert "does not exist" not in proc.stderr


def test_a_port_in_use_exits_4_not_the_models_3(tiny_checkpoint):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        proc = serve(tiny_checkpoint, "--port", str(taken.getsockname()[1]))
    assert (EXIT_BIND, EXIT_MODEL) == (4, 3)
    assert proc.returncode == EXIT_BIND, proc.stderr[-2000:]
    assert "cannot bind 127.0.0.1:" in proc.stderr and "Address already in use" in proc.stderr


def test_an_address_not_of_this_machine_exits_4_without_aborting(tiny_checkpoint):
    proc = serve(tiny_checkpoint, "--port", str(free_port()), env={"NEMSIM_HOST": "999.1.1.1"})
    assert proc.returncode == EXIT_BIND, proc.stderr[-2000:]
    assert "cannot bind 999.1.1.1:" in proc.stderr and "terminate called" not in proc.stderr
    assert "loading checkpoint" not in proc.stderr  # refused before the model loads


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_clean_stop_exits_0(sig, tiny_checkpoint, tmp_path):
    server = LiveServer(tiny_checkpoint, tmp_path / "jobs", tmp_path / "server.log",
                        env={"NEMSIM_WARMUP_STEPS": "1", "OMP_NUM_THREADS": "1"})
    try:
        server.wait_ready(timeout_s=TIMEOUT_S)
        code, _ = server.stop(sig, timeout_s=TIMEOUT_S)
    finally:
        server.stop(signal.SIGKILL, timeout_s=10)
    log = (tmp_path / "server.log").read_text()
    assert code == 0, log[-2000:]
    assert "Application shutdown complete" in log


def status(http: httpx.Client) -> str | None:
    """The loading status /ready reports (None before the server answers)."""
    try:
        return http.get("/ready").json().get("status")
    except httpx.TransportError:
        return None


@pytest.mark.slow
def test_a_stop_while_warming_up_exits_0_without_aborting(tiny_checkpoint, tmp_path):
    """The warm-up runs in a thread of the runtime's native code, which aborts an interpreter that shuts
    down under it ("terminate called without an active exception", exit 134)."""
    server = LiveServer(tiny_checkpoint, tmp_path / "jobs", tmp_path / "server.log",
                        env={"NEMSIM_WARMUP_STEPS": "100", "OMP_NUM_THREADS": "1"})
    try:
        with client(server, timeout_s=10) as http:
            deadline = time.monotonic() + TIMEOUT_S
            while status(http) != "warming-up":
                assert server.alive() and time.monotonic() < deadline, "never seen warming up"
                time.sleep(0.02)
        code, _ = server.stop(signal.SIGTERM, timeout_s=TIMEOUT_S)
    finally:
        server.stop(signal.SIGKILL, timeout_s=10)
    log = (tmp_path / "server.log").read_text()
    assert code == 0 and "terminate called" not in log, log[-2000:]
