"""One error body for every failure: ``{"detail": ..., "message": "<one line>"}``.

`detail` keeps the structure a client may parse (the list of validation errors for 422, a string
otherwise); `message` is always one readable line. Nothing in either names a file path, a library
or a stack frame: unexpected exceptions answer a generic 500 carrying the request id (the log has the
rest).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from typing import Any

import fastapi.routing
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Router
from starlette.types import Scope

log = logging.getLogger(__name__)

# FastAPI's text for a body that json.loads refused other than as invalid JSON syntax; the cause says why
_UNPARSABLE = "There was an error parsing the body"


def one_line(text: Any, limit: int = 500) -> str:
    """`text` as a single line of at most `limit` characters."""
    line = " ".join(str(text).split())
    return line if len(line) <= limit else line[: limit - 1] + "…"


def error_body(detail: Any, message: str) -> dict[str, Any]:
    return {"detail": detail, "message": one_line(message)}


def _readable(errors: list[dict]) -> list[dict]:
    """Validation errors without the offending input (it may hold NaN, which JSON cannot carry)."""
    out = []
    for e in errors:
        loc = [str(p) for p in e.get("loc", ())]
        kind = str(e.get("type", "value_error"))
        msg = str(e.get("msg", "invalid value")).removeprefix("Value error, ")
        if kind == "json_invalid":  # loc is ("body", <character offset>)
            reason = (e.get("ctx") or {}).get("error", "")
            at = loc[1] if len(loc) > 1 else "?"
            loc, msg = ["body"], f"the request body is not valid JSON (at character {at}: {reason})"
        out.append({"loc": loc, "msg": one_line(msg), "type": kind})
    return out


def unparsable_body(cause: BaseException | None) -> str:
    """What is wrong with a body FastAPI could not parse (`cause`: what json.loads raised)."""
    if isinstance(cause, UnicodeDecodeError):
        return "the request body could not be decoded: send UTF-8 encoded JSON"
    if isinstance(cause, RecursionError):
        return "the request body nests arrays or objects too deeply to parse: send a flatter JSON body"
    if isinstance(cause, ValueError) and "integer string conversion" in str(cause):
        return (
            f"the request body holds an integer of more than {sys.get_int_max_str_digits()} digits "
            "(number too large): send smaller numbers"
        )
    return "the request body could not be parsed as JSON"


def matching_routes(router: Router, scope: Scope) -> Iterator[Any]:
    """The routes whose path matches the request's (any method), in routing order, included routers
    flattened (newer FastAPI keeps them nested: `fastapi.routing.iter_route_contexts` walks them)."""
    walk = getattr(fastapi.routing, "iter_route_contexts", None)
    for route in walk(router.routes) if walk is not None else router.routes:
        if route.matches(scope)[0] is not Match.NONE:
            yield route


def allowed_methods(request: Request) -> str:
    """Every method some route serves at this path (one route per method, e.g. GET and DELETE /jobs/{id},
    while the 405 of the first route found lists only its own)."""
    methods: set[str] = set()
    for route in matching_routes(request.app.router, request.scope):
        methods |= set(getattr(route, "methods", None) or ())
    return ", ".join(sorted(methods))


async def validation_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    detail = _readable(list(exc.errors()))
    message = "; ".join(
        f"{'.'.join(d['loc'][1:] if len(d['loc']) > 1 else d['loc']) or 'body'}: {d['msg']}" for d in detail
    )
    return JSONResponse(status_code=422, content=error_body(detail, message or "invalid request"))


async def http_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, StarletteHTTPException)
    detail = exc.detail
    message = detail if isinstance(detail, str) else f"HTTP {exc.status_code}"
    headers = dict(getattr(exc, "headers", None) or {})
    if detail == _UNPARSABLE:
        detail = message = unparsable_body(exc.__cause__)
    elif exc.status_code == 404 and detail == "Not Found":
        message = f"no route {request.url.path!r}: see /docs (or /openapi.json) for the routes"
    elif exc.status_code == 405:
        message = f"{request.method} is not allowed on {request.url.path!r}"
        allow = allowed_methods(request)
        if allow:
            headers = {k: v for k, v in headers.items() if k.lower() != "allow"} | {"Allow": allow}
            message += f" (allowed: {allow})"
    return JSONResponse(
        status_code=exc.status_code, content=error_body(detail, message), headers=headers or None
    )


async def unhandled_error_handler(request: Request, exc: Exception) -> JSONResponse:
    rid = request.scope.get("state", {}).get("request_id", "-")
    log.error("unhandled error in %s %s (request %s)", request.method, request.url.path, rid, exc_info=exc)
    return JSONResponse(
        status_code=500,
        content=error_body(
            "internal error", f"internal error (request id {rid}); the server log has details"
        ),
    )


def install(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, validation_error_handler)
    app.add_exception_handler(StarletteHTTPException, http_error_handler)
    app.add_exception_handler(Exception, unhandled_error_handler)
