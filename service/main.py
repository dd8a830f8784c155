"""The FastAPI app: `create_app(settings=None)` builds it; `lifespan` loads the checkpoint and warms up.

Loading runs in a background thread so `/health` answers at once while `/ready` stays 503 until the
weights are loaded and verified and a warm-up rollout ran (what an orchestrator's readiness probe wants). A
checkpoint that cannot load (missing, empty, truncated, unsafe, damaged or non-finite weights, incompatible,
of another scene) is permanent: `/ready` reports why (without paths) and, with `exit_on_load_failure` (what
`nemsim serve` sets), the process then stops with a non-zero status so a supervisor restarts or reports it
instead of keeping a server that can never serve.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys
import threading
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass

import torch
from fastapi import FastAPI

from nemsim import __version__
from nemsim.inference import CheckpointError, load_checkpoint
from service import errors, openapi
from service.access import AccessMiddleware
from service.config import Settings, get_settings
from service.jobs import JobQueue
from service.memory import ResponseBudget, release_free_memory
from service.metrics import Metrics
from service.middleware import BodySizeLimitMiddleware, HandlerTimeoutMiddleware
from service.routes import health, inverse, jobs, mechanisms, operations, page, rollouts
from service.scheduler import Gates
from service.served_model import ServedModel

log = logging.getLogger(__name__)


@dataclass
class ServiceState:
    status: str = "starting"  # starting | loading | warming-up | ready | failed
    error: str | None = None
    served: ServedModel | None = None

    @property
    def ready(self) -> bool:
        return self.status == "ready"


LOAD_THREAD = "nemsim-load"  # the thread that loads the checkpoint and warms up (`lifespan`)
LOAD_FAILURE_EXIT = {"failed": False}  # set when a load failure stopped the process (`nemsim serve` reads it)


def stop_process() -> None:
    """Ask the server to shut down (uvicorn turns SIGTERM into a graceful exit)."""
    LOAD_FAILURE_EXIT["failed"] = True
    os.kill(os.getpid(), signal.SIGTERM)


def loading() -> bool:
    """Whether this process is still loading a checkpoint: the runtimes' native threads then abort an
    interpreter that shuts down under them, so `nemsim serve` ends such a process without that shutdown."""
    return any(t.name == LOAD_THREAD and t.is_alive() for t in threading.enumerate())


M_ARENA_MAX = -8  # glibc mallopt parameter (malloc.h)


def limit_allocator_retention() -> None:
    """At most two glibc malloc arenas (Linux/glibc; a MALLOC_* environment variable wins).

    Why: glibc gives threads their own arenas (up to eight per core), and an arena keeps the memory
    of the large arrays freed in it for reuse; the server's many short-lived threads (mesh exports,
    body parsing, rollouts) could each grow one. A fixed mmap threshold, which would return every
    large array at once, cost clearly more CPU per uncached rollout in page faults (measured; see
    benchmarks/service/README.md): not used."""
    if not sys.platform.startswith("linux") or any(k.startswith("MALLOC_") for k in os.environ):
        return
    try:
        ctypes.CDLL("libc.so.6").mallopt(M_ARENA_MAX, 2)
    except (OSError, AttributeError):  # not glibc (e.g. musl): nothing to tune
        return


def checkpoint_problem(settings: Settings) -> str | None:
    """Why the configured checkpoint can never be served (missing, unreadable, unsafe, damaged, incompatible
    or of another scene; the message names the file by its base name), or None: what `nemsim serve` checks
    once before binding, since every worker would fail the same way."""
    try:
        load_checkpoint(settings.resolved_checkpoint(), scene=settings.expected_scene())
    except CheckpointError as exc:
        return str(exc)
    return None


def load_model(state: ServiceState, settings: Settings, on_failure: Callable[[], None] | None = None) -> None:
    """Load the checkpoint and run the warm-up rollout, recording progress in `state` (never raises).

    On failure `state.error` gets a message safe for clients and `on_failure` (if any) is called."""
    path = settings.resolved_checkpoint()
    if not path.is_file():
        hint = "" if settings.checkpoint is not None else ": set NEMSIM_CHECKPOINT or NEMSIM_SCENE"
        state.status, state.error = "failed", f"checkpoint {path.name!r} not found{hint}"
        log.error("no checkpoint at %s%s", path, hint)
        if on_failure is not None:
            on_failure()
        return
    try:
        # concurrent rollouts share the cores
        share = max(1, (os.cpu_count() or 1) // settings.max_concurrency)
        torch.set_num_threads(settings.torch_threads or min(torch.get_num_threads(), share))
        state.status = "loading"
        log.info("loading checkpoint %s", path)
        served = ServedModel.from_checkpoint(
            path, scene=settings.expected_scene(), cache_size=settings.cache_size,
            cache_bytes=settings.cache_max_mb << 20, runtime_backend=settings.runtime_backend,
            runtime_precision=settings.runtime_precision, runtime_threads=settings.runtime_threads,
        )
        state.status = "warming-up"
        served.warm_up(settings.warmup_steps)
        if settings.warmup_steps > 0:
            served.warm_up_meshes()
        release_free_memory()
        state.served = served
        state.status = "ready"
        log.info("initial state: %s", served.predictor.initial_state_source)
        log.info("model %s ready", served.model_id)
    except CheckpointError as exc:
        state.status, state.error = "failed", str(exc)
        cause = f" ({type(exc.__cause__).__name__}: {exc.__cause__})" if exc.__cause__ else ""
        log.error("could not load checkpoint %s: %s%s", path, exc, cause)
    except Exception:  # noqa: BLE001 -- reported on /ready (without internals) and in the log
        state.status, state.error = "failed", "the model could not be loaded (the server log has details)"
        log.exception("could not load checkpoint %s", path)
    if state.status == "failed" and on_failure is not None:
        log.error("the checkpoint can never load: stopping the server")
        on_failure()


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    state: ServiceState = app.state.service
    app.state.jobs.open()  # remove what dead servers' jobs left; stop the job children on signals
    if state.served is None:
        threading.Thread(
            target=load_model,
            args=(state, app.state.settings, app.state.on_load_failure),
            name=LOAD_THREAD,
            daemon=True,
        ).start()
    yield
    app.state.jobs.close()
    app.state.gates.close()


def create_app(settings: Settings | None = None, served: ServedModel | None = None) -> FastAPI:
    """Build the app. `settings` replaces `get_settings()` (routes too); a given `served` model skips
    loading."""
    settings = settings or get_settings()
    limit_allocator_retention()
    app = FastAPI(
        title="NEMSim",
        version=__version__,
        description="Plasma-etch profile evolution from 14 process controls: rollouts, profile metrics, "
        "surface meshes and event-mechanism counterfactuals from a NEMSim checkpoint.",
        lifespan=lifespan,
        responses=openapi.error_responses(*openapi.COMMON_ERRORS),
        docs_url=None,  # service.openapi serves /docs from the vendored Swagger UI (offline)
        redoc_url=None,  # ReDoc loads from a CDN: /docs (vendored Swagger UI) works offline
        openapi_url="/openapi.json" if settings.docs else None,
    )
    app.state.settings = settings
    app.state.service = ServiceState()
    app.state.gates = Gates.from_settings(settings)
    app.state.jobs = JobQueue.from_settings(settings)
    app.state.response_budget = ResponseBudget(settings.response_max_mb << 20)
    app.state.on_load_failure = stop_process if settings.exit_on_load_failure else None
    if served is not None:
        app.state.service.served, app.state.service.status = served, "ready"

    app.add_middleware(BodySizeLimitMiddleware, max_bytes=settings.max_body_bytes)
    app.add_middleware(HandlerTimeoutMiddleware, timeout_s=settings.handler_timeout_s)
    app.state.metrics = Metrics()
    app.add_middleware(  # outermost
        AccessMiddleware, settings=settings, metrics=app.state.metrics, router=app.router
    )
    errors.install(app)
    openapi.install(app, settings)
    app.include_router(health.router)
    app.include_router(rollouts.router)
    app.include_router(mechanisms.router)
    app.include_router(operations.router)
    app.include_router(jobs.router)
    app.include_router(inverse.router)
    page.install(app)
    return app
