"""Event-mechanism counterfactuals: the same library function as `nemsim counterfactual`."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import Response

from nemsim.inference import Refused
from service.deps import GatesDep, ServedModelDep, SettingsDep, gated, reject, single_valued_query
from service.openapi import ErrorBody
from service.schemas import (
    MechanismsQuery,
    MechanismsResponse,
    array_to_controls,
    controls_to_array,
    json_response,
)

router = APIRouter(tags=["mechanisms"])


@router.get(
    "/mechanisms",
    response_model=MechanismsResponse,
    responses={501: {"model": ErrorBody, "description": "model without mechanisms"}},
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
    predictor = served.predictor
    if not predictor.supports_mechanisms:
        raise HTTPException(
            status_code=501,
            detail=f"model {predictor.loaded.name!r} has no event mechanisms (not a NEMSim model)",
        )
    try:
        schedule, warnings, found, clipped = predictor.check_range(
            predictor.schedule(controls_to_array(query), steps=1), settings.extrapolation
        )
    except Refused as exc:
        reject(("query",), str(exc))
    raw = schedule.raw[0]  # (14,) physical units
    result = served.cached_mechanisms(raw, query.factors)
    request.app.state.metrics.cache_lookup("mechanisms", result is not None)
    try:
        if result is None:
            result = await gated(request, gates.mechanisms, served.mechanisms, raw, query.factors)
    except ValueError as exc:  # the library rejects an input it cannot analyse, naming it
        reject(("query",), str(exc))
    return json_response(MechanismsResponse(
        model_id=served.model_id,
        controls=array_to_controls(raw),
        result=result,
        warnings=warnings,
        extrapolation=[e.as_dict() for e in found],  # type: ignore[misc]
        clipped=clipped,
    ))
