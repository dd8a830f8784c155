"""Typed dependencies shared by the routes (STYLE rule 14: a repeated check is one dependency)."""

from __future__ import annotations

from typing import Annotated, NoReturn

from fastapi import Depends, HTTPException, Request
from fastapi.exceptions import RequestValidationError

from service.config import Settings, get_settings
from service.surrogate import Surrogate


def get_surrogate(request: Request) -> Surrogate:
    """The loaded model; 503 until the checkpoint is loaded and warmed up."""
    state = request.app.state.service
    if state.surrogate is None or not state.ready:
        raise HTTPException(
            status_code=503,
            detail=f"model not ready ({state.status}{': ' + state.error if state.error else ''})",
            headers={"Retry-After": "2"},
        )
    return state.surrogate


SurrogateDep = Annotated[Surrogate, Depends(get_surrogate)]
SettingsDep = Annotated[Settings, Depends(get_settings)]


LIST_QUERY_PARAMS = frozenset({"factors"})  # the only query parameters that may repeat


def single_valued_query(request: Request) -> None:
    """422 naming a query parameter given more than once (frameworks silently keep the last one)."""
    seen: set[str] = set()
    for key, _ in request.query_params.multi_items():
        if key in seen and key not in LIST_QUERY_PARAMS:
            reject(("query", key), f"{key} is given more than once; give it once")
        seen.add(key)


def reject(loc: tuple[str | int, ...], msg: str) -> NoReturn:
    """422 in the same shape as request validation errors (one handler formats both)."""
    raise RequestValidationError([{"loc": loc, "msg": msg, "type": "value_error"}])


def busy(exc: Exception) -> NoReturn:
    """503 with Retry-After for a full compute queue."""
    raise HTTPException(status_code=503, detail=str(exc), headers={"Retry-After": "1"}) from exc
