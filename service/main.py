"""The FastAPI app: `create_app(settings=None)` builds it; `lifespan` loads the checkpoint and warms up.

Loading runs in a background thread so `/health` answers at once while `/ready` stays 503 until the
weights are loaded and a warm-up rollout ran (what an orchestrator's readiness probe wants). A missing or
broken checkpoint never crashes the process: `/ready` reports it and model routes answer 503.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass

import torch
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from nemsim import __version__
from service.config import Settings, get_settings
from service.middleware import BodySizeLimitMiddleware
from service.routes import health, mechanisms, rollouts
from service.surrogate import Surrogate

log = logging.getLogger(__name__)


@dataclass
class ServiceState:
    status: str = "starting"  # starting | loading | warming-up | ready | failed
    error: str | None = None
    surrogate: Surrogate | None = None

    @property
    def ready(self) -> bool:
        return self.status == "ready"


def load_surrogate(state: ServiceState, settings: Settings) -> None:
    """Load the checkpoint and run the warm-up rollout, recording progress in `state` (never raises)."""
    path = settings.resolved_checkpoint()
    if path is None:
        state.status, state.error = (
            "failed",
            "no checkpoint: put a *.pt under checkpoints/ or set NEMSIM_CHECKPOINT",
        )
        log.error(state.error)
        return
    try:
        if settings.torch_threads:
            torch.set_num_threads(settings.torch_threads)
        state.status = "loading"
        log.info("loading checkpoint %s", path)
        surrogate = Surrogate.from_checkpoint(
            path,
            cache_size=settings.cache_size,
            max_concurrency=settings.max_concurrency,
            max_queue=settings.max_queue,
            queue_timeout_s=settings.queue_timeout_s,
            runtime_backend=settings.runtime_backend,
            runtime_precision=settings.runtime_precision,
            runtime_threads=settings.runtime_threads,
        )
        state.status = "warming-up"
        surrogate.warm_up(settings.warmup_steps)
        state.surrogate = surrogate
        state.status = "ready"
        log.info("model %s ready", surrogate.model_id)
    except Exception as exc:  # noqa: BLE001 -- reported on /ready instead of killing the server
        state.status, state.error = "failed", f"{type(exc).__name__}: {exc}"
        log.exception("could not load checkpoint %s", path)


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    state: ServiceState = app.state.service
    if state.surrogate is None:
        threading.Thread(
            target=load_surrogate, args=(state, app.state.settings), name="nemsim-load", daemon=True
        ).start()
    yield


def _readable(errors: list[dict]) -> list[dict]:
    """Validation errors without the offending input (it may hold NaN, which JSON cannot carry)."""
    out = []
    for e in errors:
        loc = [str(p) for p in e.get("loc", ())]
        msg = str(e.get("msg", "invalid value")).removeprefix("Value error, ")
        out.append({"loc": loc, "msg": msg, "type": str(e.get("type", "value_error"))})
    return out


async def validation_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    detail = _readable(list(exc.errors()))
    message = "; ".join(
        f"{'.'.join(d['loc'][1:] if len(d['loc']) > 1 else d['loc']) or 'body'}: {d['msg']}" for d in detail
    )
    return JSONResponse(status_code=422, content={"detail": detail, "message": message})


def create_app(settings: Settings | None = None, surrogate: Surrogate | None = None) -> FastAPI:
    """Build the app. `settings` replaces `get_settings()` (routes too); a given `surrogate` skips loading."""
    settings = settings or get_settings()
    app = FastAPI(
        title="NEMSim",
        version=__version__,
        description="Plasma-etch profile evolution from 14 process controls: rollouts, profile metrics, "
        "surface meshes and event-mechanism counterfactuals from a NEMSim checkpoint.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.service = ServiceState()
    if surrogate is not None:
        app.state.service.surrogate, app.state.service.status = surrogate, "ready"
    app.dependency_overrides[get_settings] = lambda: settings
    app.add_middleware(BodySizeLimitMiddleware, max_bytes=settings.max_body_bytes)
    app.add_exception_handler(RequestValidationError, validation_error_handler)
    app.include_router(health.router)
    app.include_router(rollouts.router)
    app.include_router(mechanisms.router)
    return app
