"""Typed dependencies shared by the routes (STYLE rule 14: a repeated check is one dependency)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Annotated, Any, NoReturn, TypeVar

from fastapi import Depends, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from starlette.concurrency import run_in_threadpool

from service.config import Settings, get_settings
from service.scheduler import ClientGone, FairGate, Gates, ServiceBusy, run_gated
from service.served_model import ServedModel

log = logging.getLogger(__name__)
T = TypeVar("T")


async def get_served_model(request: Request) -> ServedModel:
    """The served model; 503 until the checkpoint is loaded and warmed up.

    The dependencies here are `async def`: FastAPI runs a plain `def` dependency in its thread pool, a
    thread hop per dependency per request that, on a core saturated by rollouts, waits for the scheduler
    each time."""
    state = request.app.state.service
    if state.served is None or not state.ready:
        raise HTTPException(
            status_code=503,
            detail=f"model not ready ({state.status}{': ' + state.error if state.error else ''})",
            headers={"Retry-After": "2"},
        )
    return state.served


ServedModelDep = Annotated[ServedModel, Depends(get_served_model)]


async def app_settings(request: Request) -> Settings:
    """The settings the app was built with (`service.main.create_app`), else the process-wide ones.

    Read from the app's state rather than set as a dependency override: while any override is set,
    FastAPI rebuilds every sub-dependency of a route (signature inspection, annotation evaluation) on every
    request."""
    settings = getattr(request.app.state, "settings", None)
    return settings if isinstance(settings, Settings) else get_settings()


SettingsDep = Annotated[Settings, Depends(app_settings)]


async def get_gates(request: Request) -> Gates:
    return request.app.state.gates


GatesDep = Annotated[Gates, Depends(get_gates)]


def client_key(request: Request) -> str:
    """Who is asking, for fair queueing and rate limits: the API key's id when keys are in use (set by
    the access middleware), else the client address."""
    state = request.scope.get("state") or {}
    if state.get("client_key"):
        return str(state["client_key"])
    client = request.scope.get("client")
    return str(client[0]) if client else "-"


async def gated(request: Request, gate: FairGate, fn: Callable[..., T], *args: Any) -> T:
    """`run_gated` with its failures as HTTP answers: 503 + Retry-After when the queue is full, 499
    (nobody reads it) when the client disconnected first."""
    try:
        return await run_gated(request, gate, client_key(request), fn, *args)
    except ServiceBusy as exc:
        busy(exc)
    except ClientGone:
        log.info("client gone before %s %s finished: dropped", request.method, request.url.path)
        raise HTTPException(status_code=499, detail="client closed the request") from None


LIST_QUERY_PARAMS = frozenset({"factors"})  # the only query parameters that may repeat


async def single_valued_query(request: Request) -> None:
    """422 naming a query parameter given more than once (frameworks silently keep the last one)."""
    seen: set[str] = set()
    for key, _ in request.query_params.multi_items():
        if key in seen and key not in LIST_QUERY_PARAMS:
            reject(("query", key), "given more than once; give it once")
        seen.add(key)


def reject(loc: tuple[str | int, ...], msg: str) -> NoReturn:
    """422 in the same shape as request validation errors (one handler formats both)."""
    raise RequestValidationError([{"loc": loc, "msg": msg, "type": "value_error"}])


async def feature_case(
    served: ServedModel, geometry: Any, loc: tuple[str | int, ...] = ("body", "geometry")
) -> Any:
    """The predictor's `FeatureCase` of a request's `geometry` block (None: the model's own feature); 422 at
    `loc` for a kind the model was not trained on or a feature that does not fit the grid. A new feature's
    initial state is built off the event loop."""
    if geometry is None:
        return served.predictor.case(None)
    try:
        return await run_in_threadpool(served.predictor.case, geometry.feature())
    except ValueError as exc:  # UnknownGeometry included: one line naming the kinds or the accepted range
        reject(loc, str(exc))


def busy(exc: Exception) -> NoReturn:
    """503 with Retry-After for a full compute queue."""
    raise HTTPException(status_code=503, detail=str(exc), headers={"Retry-After": "1"}) from exc
