"""Connection abuse against a live server: slow heads (slowloris) and one client holding many silent
sockets, each while another client (another loopback address) keeps using the server.

`slowloris`: `sockets` connections from 127.0.0.1, each sending a request head one byte per
`byte_interval_s` (never finishing it). Reported: how many the server cut within 1 s of connecting (beyond
the per-client connection cap: answered 503 + Retry-After, closed to make room for a newer one, or reset),
how many it held and then answered 408 and closed, the time from connect to cut, and the other client's
/health answers meanwhile.

`silent_sockets`: one client (127.0.0.1) opens `sockets` connections that never send a byte and reopens
each one the server closes, once per `reopen_s`; another client (`other`, e.g. 127.0.0.2, a new connection
per request) alternates GET /health and uncached POST /rollout for `seconds`. Reported: its failures and
the rollout p50, against the same client's p50 just before the attack.
"""

from __future__ import annotations

import selectors
import socket
import threading
import time
from typing import Any

import httpx
import numpy as np

from bench.live_server import LiveServer, client, percentiles_ms, random_controls

SLOW_HEAD = (
    b"POST /rollout HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nX-Slow: " + b"a" * 4096
)


def _connect(port: int, source: str = "127.0.0.1") -> socket.socket | None:
    s = socket.socket()
    try:
        s.bind((source, 0))
        s.settimeout(2.0)
        s.connect(("127.0.0.1", port))
        s.setblocking(False)
    except OSError:
        s.close()
        return None
    return s


def _state(s: socket.socket) -> str:
    """open | answered (bytes came back) | closed (EOF) | reset, without blocking."""
    try:
        data = s.recv(4096)
    except BlockingIOError:
        return "open"
    except OSError:
        return "reset"
    return "answered" if data else "closed"


class _Prober(threading.Thread):
    """Another client: GET /health (and, with `rollouts`, uncached POST /rollout) in turn, a new
    connection each time, from loopback address `source`, until `stop` is set; `pause_s` between rounds, so
    it stays within the server's default rate limit (20 requests/s per client): a client sending as fast as
    it can is throttled (429) by design, and that says nothing about the sockets under test."""

    def __init__(
        self, server: LiveServer, source: str, *, rollouts: bool, steps: int, seed: int, pause_s: float = 0.25
    ) -> None:
        super().__init__(daemon=True)
        self.server, self.source, self.rollouts, self.steps = server, source, rollouts, steps
        self.rng, self.pause_s = np.random.default_rng(seed), pause_s
        self.stop = threading.Event()
        self.health: list[float] = []
        self.rollout: list[float] = []
        self.failures: list[str] = []

    def run(self) -> None:
        with httpx.Client(
            base_url=self.server.base,
            timeout=60.0,
            limits=httpx.Limits(max_keepalive_connections=0),
            transport=httpx.HTTPTransport(local_address=self.source),
        ) as http:
            while not self.stop.is_set():
                self._one(http, "GET", "/health", None, self.health)
                if self.rollouts:
                    body = {"controls": random_controls(self.rng), "steps": self.steps}
                    self._one(http, "POST", "/rollout", body, self.rollout)
                self.stop.wait(self.pause_s)

    def _one(self, http: httpx.Client, method: str, path: str, body: Any, times: list[float]) -> None:
        t0 = time.perf_counter()
        try:
            r = http.request(method, path, json=body)
            if r.status_code == 200:
                times.append(time.perf_counter() - t0)
                return
            self.failures.append(f"{method} {path}: {r.status_code}")
        except httpx.HTTPError as exc:
            self.failures.append(f"{method} {path}: {type(exc).__name__}")

    def report(self) -> dict[str, Any]:
        return {
            "health": percentiles_ms(self.health),
            "rollout": percentiles_ms(self.rollout),
            "failures": len(self.failures),
            "failure_examples": self.failures[:5],
        }


def slowloris(
    server: LiveServer,
    *,
    sockets: int = 300,
    byte_interval_s: float = 0.5,
    cap_s: float = 60.0,
    other: str = "127.0.0.2",
) -> dict[str, Any]:
    """Slow request heads (module docstring)."""
    prober = _Prober(server, other, rollouts=False, steps=1, seed=0)
    prober.start()
    opened: dict[socket.socket, float] = {}
    failed_connects = 0
    for _ in range(sockets):
        s = _connect(server.port)
        if s is None:
            failed_connects += 1
        else:
            opened[s] = time.monotonic()
    sent = dict.fromkeys(opened, 0)
    cut: dict[str, list[float]] = {"reset": [], "closed": [], "answered": []}
    t0 = time.monotonic()
    while opened and time.monotonic() - t0 < cap_s:
        for s in list(opened):
            state = _state(s)
            if state == "open":
                try:
                    s.send(SLOW_HEAD[sent[s] : sent[s] + 1])
                    sent[s] += 1
                    continue
                except OSError:
                    state = "reset"
            cut[state].append(time.monotonic() - opened.pop(s))
            s.close()
        time.sleep(byte_interval_s)
    still_open = len(opened)
    for s in opened:
        s.close()
    prober.stop.set()
    prober.join()
    # within 1 s only the per-client cap answers (503); the head is far below its limit, timeouts are longer
    at_once = {k: sum(t < 1.0 for t in v) for k, v in cut.items()}
    held = sorted(t for k in cut for t in cut[k] if t >= 1.0)
    return {
        "sockets": sockets,
        "failed_connects": failed_connects,
        "byte_interval_s": byte_interval_s,
        "dropped_at_once": sum(at_once.values()),
        "at_once": {"answered_503": at_once["answered"], "closed": at_once["closed"],
                    "reset": at_once["reset"]},
        "held_then_cut": len(held),
        "answered_408_then_closed": len(cut["answered"]) - at_once["answered"],
        "cut_s": {"min": held[0], "p50": float(np.median(held)), "max": held[-1]} if held else None,
        "still_open_at_cap": still_open,
        "cap_s": cap_s,
        "server_alive": server.alive(),
        "other_client": prober.report(),
    }


def silent_sockets(
    server: LiveServer,
    *,
    sockets: int = 600,
    seconds: float = 30.0,
    reopen_s: float = 1.0,
    other: str = "127.0.0.2",
    steps: int = 100,
    seed: int = 5,
    reference_rollouts: int = 15,
) -> dict[str, Any]:
    """One client holds `sockets` silent connections while another works (module docstring)."""
    rng = np.random.default_rng(seed)
    ref: list[float] = []
    with client(server, source=other) as http:  # the other client's figure just before the attack
        for _ in range(reference_rollouts):
            t0 = time.perf_counter()
            r = http.post("/rollout", json={"controls": random_controls(rng), "steps": steps})
            if r.status_code == 200:
                ref.append(time.perf_counter() - t0)
    held: list[socket.socket] = [s for s in (_connect(server.port) for _ in range(sockets)) if s is not None]
    prober = _Prober(server, other, rollouts=True, steps=steps, seed=seed + 1)
    prober.start()
    sel = selectors.DefaultSelector()
    for s in held:
        sel.register(s, selectors.EVENT_READ)
    reopened, samples, t0 = 0, [], time.monotonic()
    while time.monotonic() - t0 < seconds:
        time.sleep(reopen_s)
        lost = [key.fileobj for key, _ in sel.select(timeout=0)]
        for fileobj in lost:
            sel.unregister(fileobj)
            fileobj.close()  # type: ignore[union-attr]
        samples.append(len(sel.get_map()))  # held (not yet seen closed) before reopening
        for _ in lost:
            s2 = _connect(server.port)
            if s2 is not None:
                sel.register(s2, selectors.EVENT_READ)
                reopened += 1
    prober.stop.set()
    prober.join()
    for key in list(sel.get_map().values()):
        key.fileobj.close()  # type: ignore[union-attr]
    sel.close()
    out = prober.report()
    ref_p50 = float(np.median(ref)) * 1e3 if ref else None
    return {
        "sockets": sockets,
        "seconds": seconds,
        "reopen_s": reopen_s,
        "reconnects": reopened,
        "sockets_still_open_per_second_p50": float(np.median(samples)) if samples else None,
        "other_client_source": other,
        "other_client": out,
        "reference_rollout_p50_ms": ref_p50,
        "server_alive": server.alive(),
    }
