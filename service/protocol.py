"""The HTTP/1.1 connection guard: uvicorn's h11 protocol with the limits a public server needs.

Without it a 1 MB URL or header met a bare TCP reset (h11 gives up at its buffer limit and uvicorn
closes while the client is still sending), a connection that sends nothing, a half-sent head or a
stalled body was held for as long as the client liked, and enough half-open sockets exhausted the
file limit. `GuardedH11Protocol` adds, per connection:

* a request line longer than `max_request_line_bytes` -> 414, a head longer than `max_header_bytes`
  -> 431, both as the service's JSON error body, followed by a lingering close (the rest of what the
  client sends is read and dropped for up to `LINGER_S`, so it sees the answer instead of a reset);
* a head not complete within `head_timeout_s` of the connection (or of the previous response) and a
  body not complete within `body_timeout_s` of its head -> 408 and close (a silent connection is
  just closed);
* at most `max_connections` open connections, and at most `max_connections_per_client` from one client
  address (trusted proxies exempt). A new connection beyond either cap makes room (`_make_room`): the
  server closes the connection that has waited longest without a request in progress (one that never
  sent a request first, then idle keep-alive ones; a head still arriving counts as waiting), of that
  address for its cap, of any for the global one. Only when every such connection is busy is the new one
  refused: beyond its address's cap with 503 + Retry-After (a lingering close, never a reset), beyond
  the global cap dropped at once. So sockets that never send a request (which the app never sees) cannot
  lock anyone out, not even another client on the same address (on loopback every local client shares
  127.0.0.1, the explorer page included), and the cap still bounds what one address holds.

A request h11 cannot parse gets 400 in the same JSON shape (uvicorn's own answer is plain text).
uvicorn's own settings do the rest (`nemsim serve` passes them): `timeout_keep_alive` (idle keep-alive
connections) and `h11_max_incomplete_event_size` (set just above the head limit so our check answers
first), and no `proxy_headers`: forwarded addresses are the app's to judge (`service.access`, from
configured proxies only). The cap on requests in flight is the app's, so its 503 is JSON too. The limits
come from `service.config.get_settings()`, so every worker process reads the same environment (the
connection caps are per worker process).
"""

from __future__ import annotations

import asyncio
import http
import json
import math
import time
from typing import Any, ClassVar

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol
from uvicorn.protocols.utils import get_remote_addr

from service.access import in_networks
from service.errors import error_body


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port on ``host`` that the OS reports free now (for a test or benchmark server)."""
    import socket

    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])

LINGER_S = 2.0  # read-and-drop window after an early error answer
LINGER_MAX_BYTES = 8 << 20  # ... and at most this much
DROP_LOG_S = 10.0  # at most one warning about closed or refused connections per this many seconds
CAP_RETRY_AFTER_S = 1  # Retry-After of a connection refused at its address's cap


class GuardedH11Protocol(H11Protocol):
    settings: Any = None  # a Settings to use instead of get_settings() (`with_settings`)
    # connections closed or refused by the caps since the last warning, and when it was logged (the process's)
    _drops: ClassVar[dict[str, float]] = {"count": 0, "logged_at": -math.inf}

    @classmethod
    def with_settings(cls, settings: Any) -> type[GuardedH11Protocol]:
        """This protocol bound to `settings` (in-process servers; worker processes read the env)."""
        return type(cls.__name__, (cls,), {"settings": settings})

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        from service.config import get_settings

        s = self.settings or get_settings()
        self.max_line, self.max_head = s.max_request_line_bytes, s.max_header_bytes
        self.head_timeout_s, self.body_timeout_s = s.head_timeout_s, s.body_timeout_s
        self.max_connections = s.max_connections
        self.max_per_client = s.max_connections_per_client
        self.trusted = s.trusted_proxy_networks()
        self._timer: asyncio.TimerHandle | None = None
        self._phase = "head"  # head | body | app
        self._head = bytearray()  # the head received so far (at most max_head + 1 bytes)
        self._dropping = False
        self._dropped = 0
        self._served = 0  # responses completed on this connection
        self._waiting_since = 0.0  # when it last began to wait for a request head

    # --- connection lifetime -----------------------------------------------------------------------
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        peer = get_remote_addr(transport)
        host = peer[0] if peer is not None else None
        if len(self.connections) >= self.max_connections and not self._make_room(None):
            transport.abort()
            self._warn(f"the connection cap ({self.max_connections}) is reached with every connection busy: "
                       "dropping new connections at once")
            return
        over = host is not None and not in_networks(host, self.trusted) and not self._make_room(host)
        super().connection_made(transport)
        self._await_head()
        if over:
            self._warn(f"{host} holds {self.max_per_client} busy connections (the per-client cap): "
                       "answering new ones 503")
            self._refuse(503, f"this address holds {self.max_per_client} connections with requests in "
                         "progress (the per-client cap); retry shortly",
                         (("retry-after", str(CAP_RETRY_AFTER_S)),))

    def _waiting(self) -> bool:
        """No request in progress: waiting for a head (none sent yet, idle keep-alive, or arriving)."""
        return self._phase == "head" and not self._dropping

    def _make_room(self, host: str | None) -> bool:
        """Whether a new connection from `host` (None: the global cap) fits: below the cap, or once the
        connection of that address (any, for None) that has waited longest without ever being answered,
        else longest idle, is closed. False when every such connection has a request in progress."""
        cap = self.max_connections if host is None else self.max_per_client
        if len(self.connections) < cap:
            return True  # (fewer connections in all than the cap: no need to count)
        mine = [  # (those being closed no longer count)
            c for c in self.connections
            if isinstance(c, GuardedH11Protocol) and not c.transport.is_closing()
            and (host is None or (c.client or ("",))[0] == host)
        ]
        if len(mine) < cap:
            return True
        waiting = [c for c in mine if c._waiting()]
        if not waiting:
            return False
        oldest = min(waiting, key=lambda c: (c._served > 0, c._waiting_since))
        oldest._cancel_timer()
        oldest.transport.close()
        self._warn(f"{'the connection cap' if host is None else host + ' at the per-client cap'}: closing "
                   "the connections that waited longest without a request to make room for new ones")
        return True

    def _warn(self, message: str) -> None:
        """Log `message` at most once per DROP_LOG_S (a flood must not flood the log), with the count of
        connections closed or refused since the last such warning."""
        drops = GuardedH11Protocol._drops
        drops["count"] += 1
        now = time.monotonic()
        if now - drops["logged_at"] >= DROP_LOG_S:
            self.logger.warning("%s (%d since the last such warning)", message, drops["count"])
            drops["count"], drops["logged_at"] = 0, now

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_timer()
        if self.transport is None:  # dropped by the connection cap
            return
        super().connection_lost(exc)

    def on_response_complete(self) -> None:
        self._served += 1
        super().on_response_complete()
        if not self.transport.is_closing():
            self._await_head()

    # --- reading ----------------------------------------------------------------------------------
    def data_received(self, data: bytes) -> None:
        if self._dropping:
            self._dropped += len(data)
            if self._dropped > LINGER_MAX_BYTES:
                self.transport.close()
            return
        if self.conn.their_state is h11.IDLE and self._head_too_large(data):
            return
        super().data_received(data)
        state = self.conn.their_state
        if state is h11.SEND_BODY and self._phase == "head":
            self._head.clear()
            self._phase = "body"
            self._arm(self.body_timeout_s)
        elif state is not h11.IDLE and state is not h11.SEND_BODY and self._phase != "app":
            self._head.clear()
            self._phase = "app"
            self._cancel_timer()

    def _head_too_large(self, data: bytes) -> bool:
        """Answer 414/431 (and return True) once the head in progress passes a limit."""
        self._head += data[: self.max_head + 1 - len(self._head)]
        line_end = self._head.find(b"\r\n")
        head_end = self._head.find(b"\r\n\r\n")
        line_len = line_end if line_end >= 0 else len(self._head)
        if line_len > self.max_line:
            self._refuse(414, f"the request line (URL) is longer than {self.max_line} bytes")
            return True
        head_len = head_end if head_end >= 0 else len(self._head)
        if head_len > self.max_head:
            self._refuse(431, f"the request headers are larger than {self.max_head} bytes")
            return True
        return False

    # --- timers -----------------------------------------------------------------------------------
    def _await_head(self) -> None:
        self._phase = "head"
        self._waiting_since = time.monotonic()
        self._head.clear()
        self._arm(self.head_timeout_s)

    def _arm(self, seconds: float) -> None:
        self._cancel_timer()
        self._timer = self.loop.call_later(seconds, self._timed_out)

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _timed_out(self) -> None:
        self._timer = None
        if self.transport.is_closing():
            return
        if self._phase == "head":
            if not self._head:  # nothing sent at all (or an idle keep-alive connection): just close
                self.transport.close()
                return
            self._refuse(408, f"the request head was not received within {self.head_timeout_s:g} s")
        elif self._phase == "body":
            cycle = self.cycle
            if cycle is not None and cycle.response_started:
                self.transport.close()
                return
            if cycle is not None:  # the app sees a disconnect; whatever it sends later is dropped
                cycle.disconnected = True
                cycle.message_event.set()
            self._refuse(408, f"the request body was not received within {self.body_timeout_s:g} s")

    def send_400_response(self, msg: str) -> None:  # h11 could not parse the request
        self._refuse(400, "the request is not valid HTTP/1.1")

    # --- answering early --------------------------------------------------------------------------
    def _refuse(self, status: int, message: str, headers: tuple[tuple[str, str], ...] = ()) -> None:
        self._cancel_timer()
        body = json.dumps(error_body(message, message)).encode()
        extra = "".join(f"{name}: {value}\r\n" for name, value in headers)
        head = (
            f"HTTP/1.1 {status} {http.HTTPStatus(status).phrase}\r\n"
            "content-type: application/json\r\n"
            f"content-length: {len(body)}\r\n"
            f"{extra}connection: close\r\n\r\n"
        ).encode("ascii")
        self.logger.info("%s: %d %s", self.client, status, message)
        self.transport.write(head + body)
        self._dropping = True
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.loop.call_later(LINGER_S, self.transport.close)


def uvicorn_options(settings: Any, *, bind_settings: bool = True) -> dict[str, Any]:
    """uvicorn.run / uvicorn.Config keyword arguments for the connection limits of `settings`.
    bind_settings=False (several worker processes) leaves the protocol to read the environment."""
    return {
        "http": GuardedH11Protocol.with_settings(settings) if bind_settings else GuardedH11Protocol,
        "h11_max_incomplete_event_size": max(settings.max_header_bytes, settings.max_request_line_bytes)
        + 4096,
        "timeout_keep_alive": settings.keep_alive_s,
        "proxy_headers": False,  # uvicorn would trust X-Forwarded-For from loopback; service.access decides
        "access_log": False,  # service.access writes one JSON line per request instead
    }
