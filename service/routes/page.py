"""The process explorer page at `/`, its static files under `/static` (no build step, no CDN), and the one
endpoint only the page needs: `GET /rollouts/{id}/slices`, the cross-sections through the hole axis of every
state of a cached rollout (bytes, so 101 states of `small` are ~0.5 MB of JSON: the time slider then redraws
the section without asking the server again)."""

from __future__ import annotations

import base64
from pathlib import Path as FsPath
from typing import Annotated

import numpy as np
from fastapi import APIRouter, FastAPI, Path
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool

from service.deps import ServedModelDep
from service.openapi import ErrorBody
from service.routes.rollouts import cached_rollout
from service.schemas import SlicesResponse

STATIC_DIR = FsPath(__file__).resolve().parent.parent / "static"


router = APIRouter(tags=["explorer"])


def install(app: FastAPI) -> None:
    """Serve `static/index.html` at `/` and the folder at `/static`."""

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC_DIR / "index.html", media_type="text/html")

    app.include_router(router)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")


@router.get(
    "/rollouts/{rollout_id}/slices",
    response_model=SlicesResponse,
    responses={404: {"model": ErrorBody, "description": "unknown or expired rollout id"}},
)
async def get_slices(
    rollout_id: Annotated[str, Path(max_length=64)], served: ServedModelDep
) -> SlicesResponse:
    """Cross-sections through the hole axis (the x-z plane at the opening's y) of every state of a cached
    rollout, for the explorer page: normalized SDF quantized to bytes, round((sdf + 1) * 127.5)."""
    result = cached_rollout(served, rollout_id)
    y = int(round(served.scene.opening_centre[1])) + 1  # +1: the field is padded by one voxel
    # (T+1, 2, D, H, W), off the event loop (reading the states waits while they are being stored)
    states = await run_in_threadpool(lambda: result.states.decode())
    planes = np.asarray(states[:, :, :, y, :], dtype=np.float32)  # (T+1, 2, D, W)
    q = np.round((np.clip(planes, -1.0, 1.0) + 1.0) * 127.5).astype(np.uint8)
    return SlicesResponse(
        shape=list(q.shape),
        voxel_nm=float(served.scene.voxel_nm),
        d_max_nm=float(served.scene.d_max_nm),
        data=base64.b64encode(q.tobytes()).decode("ascii"),
    )
