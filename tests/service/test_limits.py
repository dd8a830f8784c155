"""Connection limits on a real uvicorn server (defects 6, 10): 414 / 431 instead of a TCP reset, read
timeouts for silent, slow and stalled clients, a connection cap, and the handler timeout."""

from __future__ import annotations

import json
import socket
import threading
import time

import pytest


@pytest.fixture(scope="module")
def server(served, serve_in_thread):
    """A real server with tight limits over the shared surrogate; yields (host, port)."""
    from service.config import Settings
    from service.main import create_app
    settings = Settings(
        warmup_steps=0,
        max_request_line_bytes=2048,
        max_header_bytes=4096,
        head_timeout_s=1.0,
        body_timeout_s=1.0,
        max_connections=8,
    )
    app = create_app(settings, served=served)
    with serve_in_thread(app, settings) as addr:
        yield addr


def _exchange(addr, payload: bytes, *, wait_s: float = 5.0) -> bytes:
    """Send `payload` (all of it), then read until the server closes."""
    with socket.create_connection(addr, timeout=wait_s) as s:
        s.sendall(payload)
        chunks = []
        while True:
            try:
                data = s.recv(65536)
            except ConnectionResetError:
                raise AssertionError("connection reset instead of an answer") from None
            if not data:
                break
            chunks.append(data)
    return b"".join(chunks)


def _status_and_body(raw: bytes) -> tuple[int, dict]:
    head, _, body = raw.partition(b"\r\n\r\n")
    return int(head.split()[1]), json.loads(body)


def test_huge_url_414(server):
    raw = _exchange(server, b"GET /health?x=" + b"a" * 1_000_000 + b" HTTP/1.1\r\nhost: x\r\n\r\n")
    status, body = _status_and_body(raw)
    assert status == 414 and "2048" in body["message"] and body["detail"]


def test_huge_header_431(server):
    raw = _exchange(server, b"GET /health HTTP/1.1\r\nhost: x\r\nx-big: " + b"b" * 1_000_000 + b"\r\n\r\n")
    status, body = _status_and_body(raw)
    assert status == 431 and "4096" in body["message"]


def test_normal_request_still_served(server):
    raw = _exchange(server, b"GET /health HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n")
    assert raw.startswith(b"HTTP/1.1 200")


def test_silent_connection_closed(server):
    """The server closes a connection that sends nothing (else the client's 5-s read would time out)."""
    assert _exchange(server, b"", wait_s=5.0) == b""


def test_slow_head_408(server):
    status, body = _status_and_body(_exchange(server, b"GET /health HTTP/1.1\r\nhost: x\r\n"))
    assert status == 408 and "head" in body["message"]


def test_stalled_body_408(server):
    head = (
        b"POST /rollout HTTP/1.1\r\nhost: localhost\r\ncontent-type: application/json\r\n"
        b"content-length: 500\r\n\r\n"
    )
    status, body = _status_and_body(_exchange(server, head + b'{"steps": 1, '))
    assert status == 408 and "body" in body["message"]


def test_connection_cap(server):
    """At the cap a new connection closes the one that waited longest (at least CLOSE_AFTER_S) without a
    request and is served; with every connection busy (a body still arriving) it is dropped at once."""
    from service.protocol import CLOSE_AFTER_S

    held = [socket.create_connection(server, timeout=5) for _ in range(8)]
    busy: list[socket.socket] = []
    try:
        time.sleep(CLOSE_AFTER_S + 0.2)
        assert _exchange(server, b"GET /health HTTP/1.1\r\nhost: x\r\nconnection: close\r\n\r\n").startswith(
            b"HTTP/1.1 200"
        )
        assert held[0].recv(10) == b""  # the longest waiting, closed to make room
        for s in held:
            s.close()
        time.sleep(0.1)
        busy = [socket.create_connection(server, timeout=5) for _ in range(8)]
        for s in busy:
            s.sendall(b"POST /rollout HTTP/1.1\r\nhost: localhost\r\ncontent-length: 10\r\n\r\n{")
        time.sleep(0.1)
        with socket.create_connection(server, timeout=5) as extra:
            try:  # a complete request: a served connection would answer it
                extra.sendall(b"GET /health HTTP/1.1\r\nhost: x\r\n\r\n")
                answer = extra.recv(10)
            except (ConnectionResetError, BrokenPipeError):
                answer = b""
            assert answer == b""  # dropped at once, nothing answered
    finally:
        for s in held + busy:
            s.close()


def test_handler_timeout_504(make_client, served, default_controls, monkeypatch):
    compute = type(served)._compute

    def slow(self, *args):
        time.sleep(1.0)
        return compute(self, *args)

    monkeypatch.setattr(type(served), "_compute", slow)
    c = make_client(handler_timeout_s=0.2)
    r = c.post("/rollout", json={"controls": {**default_controls, "flux_cl": 0.0093}, "steps": 1})
    assert r.status_code == 504 and "0.2 s" in r.json()["message"]
    assert c.get("/health").status_code == 200
    time.sleep(1.2)  # let the abandoned computation finish before the test ends


def test_garbage_request_400_json(server):
    status, body = _status_and_body(_exchange(server, b"NOT HTTP AT ALL\r\n\r\n"))
    assert status == 400 and body["message"]


def test_requests_in_flight_capped(make_client, served, default_controls, monkeypatch):
    started, release = threading.Event(), threading.Event()
    compute = type(served)._compute

    def slow(self, *args):
        started.set()
        release.wait(20)
        return compute(self, *args)

    monkeypatch.setattr(type(served), "_compute", slow)
    c = make_client(limit_concurrency=1)
    first = threading.Thread(
        target=c.post,
        args=("/rollout",),
        kwargs={"json": {"controls": {**default_controls, "flux_cl": 0.0081}, "steps": 1}},
    )
    first.start()
    try:
        assert started.wait(10)
        r = c.get("/model")
        assert r.status_code == 503 and r.headers["retry-after"] == "1" and "in flight" in r.json()["message"]
        assert c.get("/health").status_code == 200  # probes exempt
    finally:
        release.set()
        first.join()


def test_queued_work_dropped_when_clients_leave(server, served, default_controls, monkeypatch):
    """Through a real server: clients that give up while queued leave the queue at once and their
    rollouts are never computed (defect 9: they used to hold the queue and run anyway)."""
    import httpx

    release = threading.Event()
    calls: list[int] = []
    compute = type(served)._compute

    def slow(self, *args):
        calls.append(1)
        release.wait(20)
        return compute(self, *args)

    monkeypatch.setattr(type(served), "_compute", slow)
    base = f"http://{server[0]}:{server[1]}"

    def post(flux: float, timeout: float) -> None:
        body = {"controls": {**default_controls, "flux_cl": flux}, "steps": 1}
        try:
            httpx.post(f"{base}/rollout", json=body, timeout=timeout)
        except httpx.TimeoutException:
            pass

    holder = threading.Thread(target=post, args=(0.00601, 30.0))
    holder.start()
    try:
        deadline = time.monotonic() + 10
        while not calls:
            assert time.monotonic() < deadline
            time.sleep(0.02)
        impatient = [threading.Thread(target=post, args=(0.00602 + 1e-5 * i, 0.3)) for i in range(5)]
        for t in impatient:
            t.start()
        for t in impatient:
            t.join()
        depth = 'nemsim_queue_depth{work="rollouts"}'
        deadline = time.monotonic() + 10
        while True:  # the queue empties although the slot is still held
            metrics = httpx.get(f"{base}/metrics").text
            if f"{depth} 0.0" in metrics:
                break
            assert time.monotonic() < deadline, [line for line in metrics.splitlines() if depth in line]
            time.sleep(0.05)
    finally:
        release.set()
        holder.join()
    time.sleep(0.3)
    assert len(calls) == 1  # only the holder's rollout ran
