"""Event-mechanism counterfactuals: the same library function as `nemsim counterfactual`."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Query
from fastapi.concurrency import run_in_threadpool

from service.deps import SurrogateDep, busy, reject, single_valued_query
from service.schemas import (
    MechanismsQuery,
    MechanismsResponse,
    array_to_controls,
    controls_to_array,
    jsonable,
)
from service.surrogate import ServiceBusy

router = APIRouter(tags=["mechanisms"])


@router.get(
    "/mechanisms",
    response_model=MechanismsResponse,
    responses={501: {"description": "model without mechanisms"}, 503: {"description": "busy"}},
    dependencies=[Depends(single_valued_query)],
)
async def get_mechanisms(
    query: Annotated[MechanismsQuery, Query()],  # type: ignore[valid-type]
    surrogate: SurrogateDep,
) -> MechanismsResponse:
    """Cl+ / neutral-Cl interventions around one base control: Delta M per family, Delta R, lambda, alpha."""
    if not surrogate.supports_mechanisms:
        raise HTTPException(
            status_code=501,
            detail=f"model {surrogate.loaded.name!r} has no event mechanisms (not a NEMSim model)",
        )
    raw = controls_to_array(query)
    try:
        result = await run_in_threadpool(surrogate.mechanisms, raw, query.factors)
    except ServiceBusy as exc:
        busy(exc)
    except ValueError as exc:  # the library rejects an input it cannot analyse, naming it
        reject(("query",), str(exc))
    return MechanismsResponse(
        model_id=surrogate.model_id,
        controls=array_to_controls(raw),
        result=jsonable(result),
        warnings=surrogate.warnings_for(raw[None]),
    )
