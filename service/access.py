"""The outermost middleware: request ids, access control, rate limits, security headers, access logs
and request metrics, for every request (pure ASGI, nothing buffered).

* Request id: the client's `X-Request-ID` if it is short and plain (<= 64 of [A-Za-z0-9._-]), else a
  new one; stored in `scope["state"]["request_id"]`, returned as `X-Request-ID`, in every log line and
  in 500 bodies.
* API keys (optional): with keys configured (`NEMSIM_API_KEYS`, comma-separated, and/or
  `NEMSIM_API_KEYS_FILE`, one per line) every route but /health and /ready needs a valid `X-API-Key`
  (401 otherwise; keys are compared in constant time and never logged: a key is known by the first 8
  hex digits of its SHA-256). Without keys the server answers only clients on this machine (loopback;
  403 for others) unless `NEMSIM_ALLOW_REMOTE_WITHOUT_KEY` is set; `nemsim serve` warns when it binds
  elsewhere without keys. Without keys the Host header must also name this machine (localhost or a
  loopback address, any port) or one of `NEMSIM_ALLOWED_HOSTS` (400 otherwise): a web page whose name
  an attacker re-points at 127.0.0.1 (DNS rebinding) sends its own name, and is refused.
* Client address: the TCP peer's, unless the peer is one of `NEMSIM_TRUSTED_PROXIES` (none by default;
  loopback is not trusted by itself): then the rightmost address of `NEMSIM_PROXY_HEADER`
  (X-Forwarded-For, or RFC 7239 Forwarded) that is not itself a trusted proxy, stored as the ASGI
  client. Otherwise those headers are ignored, so rotating them changes nothing.
* Rate limit per client (API key, else address): a token bucket of `rate_limit_per_minute` with bursts
  of `rate_limit_burst`; beyond it 429 with Retry-After. Probes and /metrics are exempt.
* Wrong API keys per client address: a token bucket of `key_failures_per_minute` with bursts of
  `key_failure_burst` (always on with keys); an address that used it up gets 429 with Retry-After for
  every request that needs a key, before its key is even compared, so guessing keys is slow and tells
  nothing meanwhile. A missing key does not count (it guesses nothing).
* At most `limit_concurrency` requests in flight (probes exempt); beyond it 503 with Retry-After at once.
* Security headers on every response (nosniff, no framing, no referrer, no caching of API answers, a
  strict Content-Security-Policy except on the interactive docs, which load their UI script).
* One JSON access-log line per request on the `service.access` logger (id, client, key id, method,
  route, status, ms, bytes) and the request counters/latency of `service.metrics`.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import json
import logging
import math
import re
import time
import uuid
from collections import OrderedDict
from typing import Any, NamedTuple

from starlette.routing import Router
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.config import IPNetwork, host_name
from service.errors import matching_routes
from service.middleware import send_error

log = logging.getLogger("service.access")

OPEN_PATHS = frozenset({"/health", "/ready"})  # probes: never need a key, never rate limited
UNLIMITED_PATHS = OPEN_PATHS | {"/metrics"}
DOCS_PATHS = frozenset({"/docs", "/docs/oauth2-redirect"})
_RID = re.compile(r"^[A-Za-z0-9._-]{1,64}$")
SECURITY_HEADERS = [
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
    (b"cross-origin-resource-policy", b"same-origin"),
]
API_CSP = (b"content-security-policy", b"default-src 'none'; frame-ancestors 'none'")
# the explorer page (/ and /static/): its own scripts, styles and API only; nothing inline, nothing remote
PAGE_CSP = (
    b"content-security-policy",
    b"default-src 'self'; img-src 'self' data: blob:; object-src 'none'; base-uri 'none'; "
    b"form-action 'none'; frame-ancestors 'none'",
)


def is_page(path: str) -> bool:
    return path == "/" or path.startswith("/static/")


def key_id(key: str) -> str:
    return "key:" + hashlib.sha256(key.encode()).hexdigest()[:8]


def is_loopback(host: str | None) -> bool:
    if host in ("testclient", "localhost"):  # starlette's TestClient; a name only the machine resolves
        return True
    try:
        return ipaddress.ip_address(host or "").is_loopback
    except ValueError:
        return False


def in_networks(host: str | None, networks: tuple[IPNetwork, ...]) -> bool:
    try:
        ip = ipaddress.ip_address(host or "")
    except ValueError:
        return False
    return any(ip in net for net in networks)


def _hop_address(value: str) -> str | None:
    """The IP address of one forwarded hop (`1.2.3.4`, `1.2.3.4:80`, `"[2001:db8::1]:4711"`), or None."""
    value = value.strip().strip('"')
    if value.startswith("["):
        value = value[1 : value.find("]")] if "]" in value else ""
    elif value.count(":") == 1:
        value = value.split(":", 1)[0]
    try:
        return str(ipaddress.ip_address(value))
    except ValueError:
        return None


def forwarded_hops(headers: dict[bytes, bytes], header: str) -> list[str | None]:
    """The client addresses of X-Forwarded-For (`a, b`) or Forwarded (`for=a;proto=http, for=b`), in order
    (None for a hop that is not an IP address, e.g. `unknown` or an obfuscated name)."""
    raw = headers.get(header.encode(), b"").decode("latin-1")
    if not raw.strip():
        return []
    if header == "x-forwarded-for":
        return [_hop_address(v) for v in raw.split(",")]
    hops: list[str | None] = []
    for element in raw.split(","):
        pairs = (p.split("=", 1) for p in element.split(";") if "=" in p)
        hops += [_hop_address(v) for k, v in pairs if k.strip().lower() == "for"]
    return hops


def client_address(
    peer: str | None, headers: dict[bytes, bytes], trusted: tuple[IPNetwork, ...], header: str
) -> str | None:
    """Who sent the request: `peer`, unless it is a trusted proxy; then the rightmost hop of `header` that
    is not a trusted proxy (the peer itself where a hop is unreadable, so made-up values change nothing)."""
    if not trusted or not in_networks(peer, trusted):
        return peer
    hops = forwarded_hops(headers, header)
    for hop in reversed(hops):
        if hop is None:
            return peer
        if not in_networks(hop, trusted):
            return hop
    return hops[0] if hops else peer


def host_allowed(host: bytes | None, allowed: frozenset[str]) -> bool:
    """Whether a Host header names this machine (localhost, a loopback address) or one of `allowed`
    (host names, `*` for any); a request without Host (HTTP/1.0, never a browser) passes."""
    if host is None or "*" in allowed:
        return True
    name = host_name(host.decode("latin-1"))
    if name == "localhost" or name in allowed:
        return True
    try:
        return ipaddress.ip_address(name.removeprefix("[").removesuffix("]")).is_loopback
    except ValueError:
        return False


def route_label(scope: Scope, router: Router | None) -> str:
    """The route template for logs and metrics, also for requests refused before routing ("unmatched":
    no route has that path)."""
    route = scope.get("route")
    if route is None and router is not None:
        route = next(matching_routes(router, scope), None)
    return getattr(route, "path", None) or "unmatched"


def bind_warning(host: str, keys: frozenset[str], allow_remote: bool) -> str | None:
    """The start-up warning for binding beyond loopback without API keys (None when there is nothing to
    say)."""
    if keys or is_loopback(host):
        return None
    consequence = (
        "NEMSIM_ALLOW_REMOTE_WITHOUT_KEY is set, so anyone who can reach the port can use it"
        if allow_remote
        else "every client on another machine gets 403"
    )
    return (
        f"binding {host} without API keys: {consequence}; set NEMSIM_API_KEYS (or NEMSIM_API_KEYS_FILE) "
        "to serve other machines"
    )


class TokenBuckets:
    """Per-client token buckets (at most `max_clients` remembered, least recently seen forgotten)."""

    def __init__(self, per_minute: int, burst: int, max_clients: int = 10_000) -> None:
        self.rate = per_minute / 60.0
        self.burst = float(max(burst, 1))
        self.max_clients = max_clients
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()

    def _level(self, client: str, now: float) -> tuple[float, float]:
        """(tokens of `client` now, seconds until it has one: 0 when it has)."""
        tokens, last = self._buckets.get(client, (self.burst, now))
        tokens = min(self.burst, tokens + (now - last) * self.rate)
        return tokens, 0.0 if tokens >= 1.0 else (1.0 - tokens) / self.rate

    def wait(self, client: str, now: float) -> float:
        """0 if `client` has a token now, else the seconds until it has one; takes nothing."""
        return self._level(client, now)[1]

    def take(self, client: str, now: float) -> float:
        """0 if the request may go ahead (a token is taken), else the seconds until a token is available."""
        tokens, wait = self._level(client, now)
        self._buckets.pop(client, None)
        self._buckets[client] = (tokens - 1.0 if wait == 0.0 else tokens, now)
        while len(self._buckets) > self.max_clients:
            self._buckets.popitem(last=False)
        return wait


def retry_after(wait_s: float) -> bytes:
    """A Retry-After value: whole seconds, at least 1."""
    return str(max(1, math.ceil(wait_s))).encode()


class Refusal(NamedTuple):
    """A request refused before the app sees it: status, one-line message, extra headers."""

    status: int
    message: str
    headers: tuple[tuple[bytes, bytes], ...] = ()


class AccessMiddleware:
    def __init__(self, app: ASGIApp, settings: Any, metrics: Any, router: Router | None = None) -> None:
        self.app = app
        self.router = router  # to label requests refused before routing
        self.keys = settings.api_key_set()
        self.allow_remote = settings.allow_remote_without_key
        self.allowed_hosts = settings.allowed_host_names()
        self.trusted = settings.trusted_proxy_networks()
        self.proxy_header = settings.proxy_header
        self.buckets = (
            TokenBuckets(settings.rate_limit_per_minute, settings.rate_limit_burst)
            if settings.rate_limit_per_minute > 0
            else None
        )
        self.key_failures = TokenBuckets(settings.key_failures_per_minute, settings.key_failure_burst)
        self.metrics = metrics
        self.access_log = settings.access_log
        self.max_in_flight = settings.limit_concurrency
        self.in_flight = 0

    def _client_key(self, scope: Scope, headers: dict[bytes, bytes]) -> str | Refusal:
        """Who the request is for the rate limits (API key id, else address), or why it is refused."""
        host = scope["client"][0] if scope.get("client") else None
        if not self.keys:
            if not (self.allow_remote or is_loopback(host)):
                return Refusal(
                    403, "this server has no API keys configured and answers only clients on its own machine"
                )
            if not host_allowed(headers.get(b"host"), self.allowed_hosts):
                name = host_name(headers[b"host"].decode("latin-1"))[:100]
                return Refusal(
                    400,
                    f"the Host header {name!r} does not name this server: without API keys it answers only "
                    "localhost, 127.0.0.1 and [::1] (a guard against DNS rebinding); add the name to "
                    "NEMSIM_ALLOWED_HOSTS to serve it",
                )
            return host or "-"
        address, now = host or "-", time.monotonic()
        wait = self.key_failures.wait(address, now)
        if wait > 0:  # checked before the key, so guessing gets no answer at all while it lasts
            retry = retry_after(wait)
            return Refusal(
                429,
                f"too many wrong API keys from this address; retry in {retry.decode()} s",
                ((b"retry-after", retry),),
            )
        given = headers.get(b"x-api-key", b"").decode("latin-1")
        if given and any(hmac.compare_digest(given.encode(), k.encode()) for k in self.keys):
            return key_id(given)
        if not given:
            return Refusal(401, "a valid X-API-Key header is required")
        self.key_failures.take(address, now)
        return Refusal(401, "the X-API-Key is not valid")

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        t0 = time.perf_counter()
        headers = dict(scope.get("headers") or [])
        given_rid = headers.get(b"x-request-id", b"").decode("latin-1")
        rid = given_rid if _RID.match(given_rid) else uuid.uuid4().hex[:16]
        state = scope.setdefault("state", {})
        state["request_id"] = rid
        path = scope.get("path", "")
        peer = scope["client"][0] if scope.get("client") else None
        address = client_address(peer, headers, self.trusted, self.proxy_header)
        if address != peer:
            scope["client"] = (address, 0)
        status, size = 500, 0
        extra = [(b"x-request-id", rid.encode()), *SECURITY_HEADERS]
        if is_page(path):
            extra.append(PAGE_CSP)
            extra.append((b"cache-control", b"no-cache"))
        elif path not in DOCS_PATHS:
            extra.append(API_CSP)
            extra.append((b"cache-control", b"no-store"))

        async def send_with_headers(message: Message) -> None:
            nonlocal status, size
            if message["type"] == "http.response.start":
                status = int(message["status"])
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            elif message["type"] == "http.response.body":
                size += len(message.get("body", b""))
            await send(message)

        client: str | Refusal = scope["client"][0] if scope.get("client") else "-"
        if path not in OPEN_PATHS:
            client = self._client_key(scope, headers)
        try:
            if isinstance(client, Refusal):
                await send_error(send_with_headers, client.status, client.message, list(client.headers))
                return
            state["client_key"] = client
            if self.buckets is not None and path not in UNLIMITED_PATHS:
                wait = self.buckets.take(client, time.monotonic())
                if wait > 0:
                    retry = retry_after(wait)
                    await send_error(
                        send_with_headers,
                        429,
                        f"rate limit exceeded for this client; retry in {retry.decode()} s",
                        [(b"retry-after", retry)],
                    )
                    return
            if path not in OPEN_PATHS and self.in_flight >= self.max_in_flight:
                await send_error(
                    send_with_headers,
                    503,
                    f"{self.in_flight} requests are in flight (the server's limit); retry shortly",
                    [(b"retry-after", b"1")],
                )
                return
            self.in_flight += 1
            try:
                await self.app(scope, receive, send_with_headers)
            finally:
                self.in_flight -= 1
        finally:
            seconds = time.perf_counter() - t0
            route = route_label(scope, self.router)
            self.metrics.observe_request(scope.get("method", "-"), route, status, seconds)
            if self.access_log:
                log.info(
                    json.dumps(
                        {
                            "request_id": rid,
                            "client": scope["client"][0] if scope.get("client") else None,
                            "key": client if isinstance(client, str) and client.startswith("key:") else None,
                            "method": scope.get("method"),
                            "route": route,
                            "path": path[:200],
                            "status": status,
                            "ms": round(seconds * 1e3, 2),
                            "bytes": size,
                        }
                    )
                )
