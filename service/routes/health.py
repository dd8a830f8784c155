"""Liveness, readiness and what model is being served."""

from __future__ import annotations

import math
from pathlib import PurePath
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from nemsim.controls import CONTROL_SPECS
from service.deps import ServedModelDep, SettingsDep
from service.schemas import ControlInfo, Health, ModelInfo, default_controls_raw, jsonable

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health)
async def get_health(request: Request) -> Health:
    """The process is alive (liveness); `model_id` once the model is served, `detail` the loading stage."""
    state = request.app.state.service
    return Health(  # type: ignore[call-arg]
        status="ok",
        model_id=state.served.model_id if state.ready else None,
        detail=None if state.ready else state.status,
    )


@router.get("/ready", response_model=Health, responses={503: {"model": Health}})
async def get_ready(request: Request) -> Health | JSONResponse:
    """200 once the checkpoint is loaded and a warm-up rollout ran, else 503 with the reason."""
    state = request.app.state.service
    if state.ready:
        return Health(status="ready", model_id=state.served.model_id)  # type: ignore[call-arg]
    reason = state.error or "the checkpoint is still loading"
    body = Health(
        status=state.status, detail=state.error, message=f"model not ready ({state.status}): {reason}"
    )
    return JSONResponse(status_code=503, content=body.model_dump(), headers={"Retry-After": "2"})


PER_CASE_KEYS = ("case_ids", "_per_case")  # long per-test-case lists: not what a client needs


def public_record(value: Any) -> Any:
    """A checkpoint's summary/metrics as shown on /model: per-case lists dropped, file paths reduced to
    their base names (a developer's run directory is nobody's business)."""
    if isinstance(value, dict):
        return {
            k: public_record(v)
            for k, v in value.items()
            if not (isinstance(v, list) and any(k.endswith(s) for s in PER_CASE_KEYS))
        }
    if isinstance(value, list):
        return [public_record(v) for v in value]
    if isinstance(value, str) and ("/" in value or "\\" in value):
        return PurePath(value.replace("\\", "/")).name
    return value


@router.get("/model", response_model=ModelInfo)
async def get_model(served: ServedModelDep, settings: SettingsDep) -> ModelInfo:
    """Checkpoint id, scene, rules SHA-256, training summary, test metrics, the controls' and the geometry's
    trained ranges."""
    predictor = served.predictor
    loaded = predictor.loaded
    controls = [
        ControlInfo(
            name=s.name,
            unit=s.unit,
            kind=s.kind,
            min=s.phys_min if math.isfinite(s.phys_min) else None,
            max=s.phys_max if math.isfinite(s.phys_max) else None,
            train_min=predictor.train_range[s.name][0],
            train_max=predictor.train_range[s.name][1],
            label=s.label,
            description=s.description,
            default=float(default),
        )
        for s, default in zip(CONTROL_SPECS, default_controls_raw(), strict=True)
    ]
    scene = jsonable(vars(predictor.scene))
    scene["state_shape"] = list(predictor.scene.state_shape)
    return ModelInfo(
        model_id=served.model_id,
        checkpoint=loaded.path.name if loaded.path else "",
        model_name=loaded.name,
        n_params=predictor.n_params,
        scene=scene,
        rules_sha256=str(loaded.rules.sha256),
        max_steps=settings.max_steps,
        horizon_steps=predictor.horizon_steps,
        summary=public_record(jsonable(loaded.summary)),
        metrics=public_record(jsonable(loaded.metrics)),
        controls=controls,
        initial_state=predictor.initial_state_source,
        extrapolation=settings.extrapolation,
        geometry={"default": predictor.case(None).feature.to_dict(), **predictor.geometry.as_dict()},
        runtime=predictor.runtime_info(),
    )
