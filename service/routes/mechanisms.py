"""Event-mechanism counterfactuals: the same library function as `nemsim counterfactual`.

`GET /mechanisms` takes the base controls as query parameters (the model's own feature); `POST /mechanisms`
takes them as a JSON body with a `geometry` block, so the feature analysed can be chosen too."""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import Response

from nemsim.inference import Refused
from service.deps import (
    GatesDep,
    ServedModelDep,
    SettingsDep,
    feature_case,
    gated,
    reject,
    single_valued_query,
)
from service.openapi import ErrorBody
from service.scheduler import Gates
from service.schemas import (
    MechanismsQuery,
    MechanismsRequest,
    MechanismsResponse,
    array_to_controls,
    controls_to_array,
    json_response,
)
from service.served_model import ServedModel

router = APIRouter(tags=["mechanisms"])
NOT_NEMSIM = {501: {"model": ErrorBody, "description": "model without mechanisms"}}


async def _mechanisms(
    request: Request,
    served: ServedModel,
    gates: Gates,
    policy: str,
    controls: np.ndarray,
    factors: list[float] | None,
    case: Any,
    loc: tuple[str, ...],
) -> Response:
    """The answer of both routes: `controls` (14,) physical units on `case` (a FeatureCase)."""
    predictor = served.predictor
    if not predictor.supports_mechanisms:
        raise HTTPException(
            status_code=501,
            detail=f"model {predictor.loaded.name!r} has no event mechanisms (not a NEMSim model)",
        )
    try:
        schedule, warnings, found, clipped = predictor.check_range(
            predictor.schedule(controls, steps=1), policy
        )
    except Refused as exc:
        reject(loc, str(exc))
    outside = predictor.geometry_outside(case.feature)
    if outside is not None:
        warnings.append(outside)
    raw = schedule.raw[0]  # (14,) physical units
    result = served.cached_mechanisms(raw, factors, case)
    request.app.state.metrics.cache_lookup("mechanisms", result is not None)
    try:
        if result is None:
            result = await gated(request, gates.mechanisms, served.mechanisms, raw, factors, case)
    except ValueError as exc:  # the library rejects an input it cannot analyse, naming it
        reject(loc, str(exc))
    return json_response(MechanismsResponse(
        model_id=served.model_id,
        controls=array_to_controls(raw),
        geometry=case.feature.to_dict(),
        result=result,
        warnings=warnings,
        extrapolation=[e.as_dict() for e in found],  # type: ignore[misc]
        clipped=clipped,
    ))


@router.get(
    "/mechanisms",
    response_model=MechanismsResponse,
    responses=NOT_NEMSIM,  # type: ignore[arg-type]
    dependencies=[Depends(single_valued_query)],
)
async def get_mechanisms(
    request: Request,
    query: Annotated[MechanismsQuery, Query()],  # type: ignore[valid-type]
    served: ServedModelDep,
    settings: SettingsDep,
    gates: GatesDep,
) -> Response:
    """Cl+ / neutral-Cl interventions around one base control: Delta M per family, Delta R, lambda, alpha."""
    case = served.predictor.case(None)
    return await _mechanisms(request, served, gates, settings.extrapolation, controls_to_array(query),
                             query.factors, case, ("query",))  # fmt: skip


@router.post("/mechanisms", response_model=MechanismsResponse, responses=NOT_NEMSIM)  # type: ignore[arg-type]
async def post_mechanisms(
    request: Request, body: MechanismsRequest, served: ServedModelDep, settings: SettingsDep, gates: GatesDep
) -> Response:
    """As GET /mechanisms, the controls, factors and the feature (`geometry`) in a JSON body."""
    case = await feature_case(served, body.geometry)
    return await _mechanisms(request, served, gates, settings.extrapolation, controls_to_array(body.controls),
                             body.factors, case, ("body", "controls"))  # fmt: skip
