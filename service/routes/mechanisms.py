"""Event-mechanism counterfactuals: the same library function as `nemsim counterfactual`."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query, Request

from service.deps import GatesDep, SurrogateDep, gated, reject, single_valued_query
from service.openapi import ErrorBody
from service.schemas import (
    MechanismsQuery,
    MechanismsResponse,
    array_to_controls,
    controls_to_array,
    jsonable,
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
    surrogate: SurrogateDep,
    gates: GatesDep,
) -> MechanismsResponse:
    """Cl+ / neutral-Cl interventions around one base control: Delta M per family, Delta R, lambda, alpha."""
    if not surrogate.supports_mechanisms:
        raise HTTPException(
            status_code=501,
            detail=f"model {surrogate.loaded.name!r} has no event mechanisms (not a NEMSim model)",
        )
    raw = controls_to_array(query)
    result = surrogate.cached_mechanisms(raw, query.factors)
    try:
        if result is None:
            result = await gated(request, gates.mechanisms, surrogate.mechanisms, raw, query.factors)
    except ValueError as exc:  # the library rejects an input it cannot analyse, naming it
        reject(("query",), str(exc))
    return MechanismsResponse(
        model_id=surrogate.model_id,
        controls=array_to_controls(raw),
        result=jsonable(result),
        warnings=surrogate.warnings_for(raw[None]),
    )
