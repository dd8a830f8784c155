"""One error body for every failure: ``{"detail": ..., "message": "<one line>"}``.

`detail` keeps the structure a client may parse (the list of validation errors for 422, a string
otherwise); `message` is always one readable line. Nothing in either names a file path, a library
or a stack frame: unexpected exceptions answer a generic 500 carrying the request id (the log has the
rest).
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger(__name__)

# FastAPI's text for a body that is not even decodable (e.g. invalid UTF-8)
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
    if detail == _UNPARSABLE:
        detail = message = "the request body could not be decoded: send UTF-8 encoded JSON"
    elif exc.status_code == 404 and detail == "Not Found":
        message = f"no route {request.url.path!r}: see /docs (or /openapi.json) for the routes"
    elif exc.status_code == 405:
        message = f"{request.method} is not allowed on {request.url.path!r}"
    return JSONResponse(
        status_code=exc.status_code,
        content=error_body(detail, message),
        headers=getattr(exc, "headers", None),
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
