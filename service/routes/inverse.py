"""Inverse design: `POST /design` (202 + Location; `GET /jobs/{id}` for progress and the result)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from nemsim.analysis.inverse import REFINE_WITH_VERIFY, check_targets, refine_config_from_dict, spec_from_dict
from service.deps import ServedModelDep, SettingsDep, feature_case, reject
from service.inverse import design_work
from service.inverse_schemas import DesignRequest
from service.routes.jobs import JOB_LIMIT_RESPONSES, JobsDep, submit_job
from service.schemas import JobCreated

router = APIRouter(tags=["design"])


@router.post(
    "/design",
    status_code=202,
    response_model=JobCreated,
    responses=JOB_LIMIT_RESPONSES,
)
async def post_design(
    request: Request,
    body: DesignRequest,
    served: ServedModelDep,
    settings: SettingsDep,
    jobs: JobsDep,
) -> JSONResponse:
    """Find recipes whose predicted profile meets the targets (a job: poll its Location).

    The result lists `k` ranked recipes with predicted metrics, conformal intervals (cut to each metric's
    physical range), a distance-to-training-data flag and the search's cost; `status` is `met` or
    `unreachable` (then the closest recipe and its miss). Each recipe's `verdict` keeps the surrogate's word
    apart from the simulator's: `predicted` / `predicted_miss` (not simulated), `confirmed` /
    `simulator_miss` (simulated), with `intervals_within_tolerance` per interval level. With `verify`,
    the simulator runs the top recipes and the result reports achieved against target.
    With `refine`, the simulator works inside the design loop (simulator-corrected rounds); the status is
    then `verified`, `unverified` or `unreachable` and the top recipe is the best simulated one. Every
    result reports `simulator_calls` (the simulator runs the design made) and, when the benchmark
    `nemsim bench design-cost` has a committed result for the served checkpoint,
    `expected_calls_to_target` (its simulator calls per target reached: one average for every design, as
    `expected_calls_basis` says). While it runs, `GET /jobs/{id}` reports its `phase`. With `geometry`,
    the recipe is searched for that feature (the model's own when left out); the result's `geometry` says
    whether it lies in the trained ranges (outside: every recipe is `ood`).
    """
    try:
        spec = spec_from_dict(body.spec_dict())
    except ValueError as exc:
        reject(("body",), str(exc))
    case = await feature_case(served, body.geometry)
    try:  # the physical ranges of the targets in the scene of the feature (its Si and mask thickness)
        check_targets(spec.targets, case.scene)
    except ValueError as exc:
        reject(("body", "targets"), str(exc))
    refine = None
    if body.refine or (body.refine is None and body.verify and REFINE_WITH_VERIFY):
        given = {"verify_top": body.verify_top, "rounds": body.refine_rounds}
        refine = refine_config_from_dict({k: v for k, v in given.items() if v is not None})
    horizon = served.predictor.horizon_steps
    if spec.step is not None and spec.step > horizon:
        reject(("body", "step"), f"step = {spec.step} is beyond the model's horizon of {horizon}")
    job = submit_job(
        request,
        jobs,
        "design",
        lambda j: design_work(
            j,
            served,
            spec,
            seed=body.seed,
            verify=body.verify,
            verify_top=body.verify_top or 1,
            sim_seed=body.sim_seed,
            sim_max_work=settings.sim_max_work,
            refine=refine,
            case=case,
        ),
    )
    location = f"/jobs/{job.id}"
    created = JobCreated(id=job.id, kind=job.kind, status=job.status, location=location,
                         geometry=case.feature.to_dict())  # fmt: skip
    return JSONResponse(status_code=202, content=created.model_dump(), headers={"Location": location})
