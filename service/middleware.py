"""Plain ASGI middlewares (no BaseHTTPMiddleware: they must not buffer or re-order messages).

* `BodySizeLimitMiddleware`: 413 before anything parses an oversized body. Checks the declared
  Content-Length first, then counts the streamed bytes (chunked uploads or a lying header), so no
  request can make the server buffer more than `max_bytes`.
* `HandlerTimeoutMiddleware`: a request not answered within `timeout_s` gets 504; the handler is
  cancelled (work already running in a thread finishes in the background and is cached).
"""

from __future__ import annotations

import asyncio
import json
import logging

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import error_body

log = logging.getLogger(__name__)


async def send_error(send: Send, status: int, message: str, headers: list[tuple[bytes, bytes]] = ()) -> None:  # type: ignore[assignment]
    """A complete JSON error response in the service's error shape."""
    body = json.dumps(error_body(message, message)).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class BodyTooLarge(HTTPException):
    """Raised from `receive` once the streamed body passes the limit; FastAPI re-raises HTTPExceptions
    from body parsing, and the app's exception middleware turns it into the 413 response."""

    def __init__(self, max_bytes: int) -> None:
        super().__init__(status_code=413, detail=f"request body too large: the limit is {max_bytes} bytes")


class BodySizeLimitMiddleware:
    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None:
            try:
                too_large = int(declared) > self.max_bytes
            except ValueError:
                await self._reply(send, 400, "Content-Length is not an integer")
                return
            if too_large:
                await self._reply(send, 413, BodyTooLarge(self.max_bytes).detail)
                return

        received = 0
        started = False

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise BodyTooLarge(self.max_bytes)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyTooLarge as exc:
            if not started:
                await self._reply(send, 413, exc.detail)

    @staticmethod
    async def _reply(send: Send, status: int, detail: str) -> None:
        await send_error(send, status, detail)


class HandlerTimeoutMiddleware:
    def __init__(self, app: ASGIApp, timeout_s: float) -> None:
        self.app = app
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = timed_out = False

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if timed_out:
                return  # the client already has its 504
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        task = asyncio.ensure_future(self.app(scope, receive, guarded_send))
        try:
            done, _ = await asyncio.wait({task}, timeout=self.timeout_s)
        except asyncio.CancelledError:
            task.cancel()
            raise
        if task in done:
            task.result()  # re-raise what the app raised
            return
        timed_out = True
        log.warning(
            "%s %s not answered within %g s: 504", scope.get("method"), scope.get("path"), self.timeout_s
        )
        task.cancel()
        task.add_done_callback(lambda t: t.cancelled() or t.exception())  # retrieve, never re-raise
        if not started:
            await send_error(
                send, 504, f"no answer within {self.timeout_s:g} s (the server's handler timeout)"
            )
