"""Liveness, readiness and what model is being served."""

from __future__ import annotations

import math

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from nemsim.controls import CONTROL_SPECS
from service.deps import SettingsDep, SurrogateDep
from service.schemas import ControlInfo, Health, ModelInfo, jsonable

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health)
def get_health() -> Health:
    """The process is alive (says nothing about the model)."""
    return Health(status="ok")


@router.get("/ready", response_model=Health, responses={503: {"model": Health}})
def get_ready(request: Request) -> Health | JSONResponse:
    """200 once the checkpoint is loaded and a warm-up rollout ran, else 503 with the reason."""
    state = request.app.state.service
    if state.ready:
        return Health(status="ready", model_id=state.surrogate.model_id)
    body = Health(status=state.status, detail=state.error)
    return JSONResponse(status_code=503, content=body.model_dump(), headers={"Retry-After": "2"})


@router.get("/model", response_model=ModelInfo)
def get_model(surrogate: SurrogateDep, settings: SettingsDep) -> ModelInfo:
    """Checkpoint id, scene, rules SHA-256, training summary, test metrics and the controls' ranges."""
    loaded = surrogate.loaded
    controls = [
        ControlInfo(
            name=s.name,
            unit=s.unit,
            kind=s.kind,
            min=s.phys_min if math.isfinite(s.phys_min) else None,
            max=s.phys_max if math.isfinite(s.phys_max) else None,
            train_min=surrogate.train_range[s.name][0],
            train_max=surrogate.train_range[s.name][1],
        )
        for s in CONTROL_SPECS
    ]
    scene = jsonable(vars(surrogate.scene))
    scene["state_shape"] = list(surrogate.scene.state_shape)
    return ModelInfo(
        model_id=surrogate.model_id,
        checkpoint=loaded.path.name if loaded.path else "",
        model_name=loaded.name,
        n_params=surrogate.n_params,
        scene=scene,
        rules_sha256=str(loaded.rules.sha256),
        max_steps=settings.max_steps,
        horizon_steps=surrogate.horizon_steps,
        summary=jsonable(loaded.summary),
        metrics=jsonable(loaded.metrics),
        controls=controls,
    )
