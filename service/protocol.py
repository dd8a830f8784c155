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
* at most `max_connections_per_client` connections served per client address (trusted proxies exempt).
  A connection beyond them waits for its first request (`_take_slot`), which then closes that address's
  connection that has waited longest without a request in progress (one never answered first, then idle
  keep-alive ones; a head still arriving counts as waiting) and takes its place, provided that one has
  waited at least `CLOSE_AFTER_S` (a connection accepted a moment earlier, in a burst of clients
  connecting at once, may have its request on the way: closing it would reset that client); with none
  such, the request is answered 503 + Retry-After (a lingering close, never a reset). Sockets that never
  send a request (which the app never sees) therefore displace nobody, however fast they are reopened,
  and lock nobody out, not even another client on the same address (on loopback every local client
  shares 127.0.0.1, the explorer page included);
* at most `max_connections` open connections in all. A new one beyond them closes, first, the oldest one
  being refused (answered already), else the oldest one waiting beyond its address's cap (it has sent
  nothing), else as above among all; with none such it is dropped at once.

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
CLOSE_AFTER_S = 0.5  # a connection is closed to make room only once it has waited this long for a request


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
        self._host: str | None = None  # the client's address
        self._slot = True  # counts toward its address's cap (set in connection_made, taken in _take_slot)
        self._dropping = False
        self._dropped = 0
        self._served = 0  # responses completed on this connection
        self._waiting_since = 0.0  # when it last began to wait for a request head

    # --- connection lifetime -----------------------------------------------------------------------
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        if len(self.connections) >= self.max_connections and not self._make_room():
            transport.abort()
            self._warn(f"the connection cap ({self.max_connections}) is reached with every connection busy "
                       "or just opened: dropping new connections at once")
            return
        super().connection_made(transport)
        self._host = (self.client or (None,))[0]
        # beyond its address's cap it waits, without a place under the cap, for its request (`_take_slot`)
        self._slot = self._host is None or in_networks(self._host, self.trusted)
        self._slot = self._slot or len(self._slot_holders()) < self.max_per_client
        self._await_head()

    def _slot_holders(self) -> list[GuardedH11Protocol]:
        """The open connections that count toward this one's address's cap (those refused do not)."""
        return [
            c for c in self.connections
            if isinstance(c, GuardedH11Protocol) and c._slot and not c._dropping
            and not c.transport.is_closing() and c._host == self._host
        ]

    def _take_slot(self) -> bool:
        """Give this connection, now sending its first request, a place under its address's cap: a free
        one, else that of the connection of that address that has waited longest (at least
        `CLOSE_AFTER_S`) without ever being answered, else longest idle, closed. False when none qualifies.
        (Taking places only for requests, never at connect, means sockets that never send one cannot
        displace anybody, however fast they are reopened.)"""
        holders = self._slot_holders()
        if len(holders) >= self.max_per_client and not self._close_one(holders, f"{self._host} at the "
                                                                        "per-client cap"):
            return False
        self._slot = True
        return True

    def _make_room(self) -> bool:
        """Whether a new connection fits under the global cap: below it, or once one connection is closed:
        the oldest one being refused (already answered), else the oldest one beyond its address's cap
        (which has sent nothing yet), else as `_take_slot` picks among all. False when none qualifies."""
        if len(self.connections) < self.max_connections:
            return True  # (fewer connections in all than the cap: no need to count)
        live = [
            c for c in self.connections if isinstance(c, GuardedH11Protocol) and not c.transport.is_closing()
        ]
        return len(live) < self.max_connections or self._close_one(live, "the connection cap")

    def _close_one(self, candidates: list[GuardedH11Protocol], where: str) -> bool:
        """Close the first of `candidates` in the order `_make_room` gives, among those being refused,
        without a place under their address's cap, or waiting at least `CLOSE_AFTER_S` without a request
        in progress (a connection accepted a moment earlier may have its request on the way). False when
        none of them qualifies."""
        since = time.monotonic() - CLOSE_AFTER_S
        victims = [
            c for c in candidates
            if c._dropping or not c._slot or (c._phase == "head" and c._waiting_since <= since)
        ]
        if not victims:
            return False
        victim = min(victims, key=lambda c: (not c._dropping, c._slot, c._served > 0, c._waiting_since))
        victim._cancel_timer()
        victim.transport.close()
        self._warn(f"{where}: closing the connections that waited longest without a request to make room "
                   "for new ones")
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
        if not (self._slot or self._dropping or self._take_slot()):
            self._warn(f"{self._host} holds {self.max_per_client} connections, each busy or just opened "
                       "(the per-client cap): answering new ones 503")
            self._refuse(503, f"this address holds {self.max_per_client} connections with requests in "
                         "progress or just opened (the per-client cap); retry shortly",
                         (("retry-after", str(CAP_RETRY_AFTER_S)),))
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
