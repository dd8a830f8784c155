"""Simulator jobs: `POST /simulations` (202 + Location), `GET /jobs/{id}`, `DELETE /jobs/{id}`, and the
surrogate-error mesh of a finished simulator job. `submit_job` is how every job route queues its work:
a client at its job limit gets 429 + Retry-After, a full queue 503 + Retry-After."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any

import anyio.to_thread
from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request
from fastapi.responses import JSONResponse, Response

from nemsim.evaluation.truth import particle_work
from nemsim.inference import MEDIA_TYPES, Refused
from service.deps import (
    ServedModelDep,
    SettingsDep,
    busy,
    client_key,
    feature_case,
    reject,
    single_valued_query,
)
from service.jobs import Job, JobQueue, TooManyJobs, UnknownJob, error_mesh, simulate_and_compare
from service.openapi import ErrorBody
from service.scheduler import ServiceBusy
from service.schemas import Channel, JobCreated, JobStatus, MeshFormat, SimulationRequest, array_to_controls

router = APIRouter(tags=["jobs"])

JobId = Annotated[str, Path(max_length=64)]
CANCEL_WAIT_S = 10.0  # DELETE waits at most this long for a running job to stop (its child is polled often)


async def get_jobs(request: Request) -> JobQueue:
    return request.app.state.jobs


JobsDep = Annotated[JobQueue, Depends(get_jobs)]


JOB_LIMIT_RESPONSES: dict[int | str, dict[str, Any]] = {
    429: {"model": ErrorBody, "description": "this client already has its limit of jobs (Retry-After)"},
    503: {"model": ErrorBody, "description": "the job queue is full (Retry-After)"},
}


def submit_job(request: Request, jobs: JobQueue, kind: str, work: Callable[[Job], dict[str, Any]]) -> Job:
    """Queue `work` for the requesting client (the rate limiter's identity): 429 + Retry-After at the
    client's job limit, 503 + Retry-After when the queue is full."""
    try:
        return jobs.submit(kind, work, client=client_key(request))
    except TooManyJobs as exc:
        raise HTTPException(
            status_code=429, detail=str(exc), headers={"Retry-After": str(exc.retry_after_s)}
        ) from exc
    except ServiceBusy as exc:
        busy(exc)


def _job(jobs: JobQueue, job_id: str) -> Job:
    try:
        return jobs.get(job_id)
    except UnknownJob:
        raise HTTPException(
            status_code=404,
            detail=f"unknown job id {job_id!r} (never created here, or finished long enough ago to be "
            "forgotten)",
        ) from None


@router.post(
    "/simulations",
    status_code=202,
    response_model=JobCreated,
    responses=JOB_LIMIT_RESPONSES,
)
async def post_simulation(
    request: Request,
    body: SimulationRequest,
    served: ServedModelDep,
    settings: SettingsDep,
    jobs: JobsDep,
) -> JSONResponse:
    """Run the simulator on the feature (default: the model's own) for these controls and compare the
    surrogate with it; a trench runs on its cross-section."""
    assert body.steps is not None  # resolved by the validator
    case = await feature_case(served, body.geometry)
    horizon = served.predictor.horizon_steps
    if body.steps > horizon:
        reject(("body", "steps"), f"steps = {body.steps} exceeds the simulator's horizon of {horizon}")
    try:
        schedule, _, _, _ = served.predictor.check_range(body.schedule(), settings.extrapolation)
    except Refused as exc:
        reject(("body", body.source), str(exc))
    if body.steps > settings.max_steps:
        reject(
            ("body", "steps"), f"steps = {body.steps} exceeds this server's ceiling of {settings.max_steps}"
        )
    # simulated particles scale with the total flux: bound the work one job may ask for
    work = particle_work([(row, 0) for row in schedule.raw]) / horizon
    if work > settings.sim_max_work:
        reject(
            ("body", body.source),
            f"this simulation is {work:.3g}x the work of a design-centre run; this server simulates at most "
            f"{settings.sim_max_work:g}x (lower the fluxes or the steps)",
        )
    seed = body.seed
    job = submit_job(
        request, jobs, "simulation", lambda j: simulate_and_compare(j, served, schedule, seed, case)
    )
    location = f"/jobs/{job.id}"
    created = JobCreated(id=job.id, kind=job.kind, status=job.status, location=location,
                         controls=array_to_controls(schedule.raw[0]), defaulted=body.defaulted,
                         geometry=case.feature.to_dict())  # fmt: skip
    return JSONResponse(status_code=202, content=created.model_dump(), headers={"Location": location})


@router.get("/jobs/{job_id}", response_model=JobStatus, responses={404: {"model": ErrorBody}})
async def get_job(job_id: JobId, jobs: JobsDep) -> JobStatus:
    """Status, progress in [0, 1] and, when done, the result."""
    return JobStatus(**_job(jobs, job_id).as_dict())


@router.delete("/jobs/{job_id}", response_model=JobStatus, responses={404: {"model": ErrorBody}})
async def delete_job(job_id: JobId, jobs: JobsDep) -> JobStatus:
    """Cancel a job; once stopped it reads `cancelled`, here and at GET /jobs/{id}, until forgotten (404)."""
    _job(jobs, job_id)
    job = await anyio.to_thread.run_sync(jobs.cancel, job_id, CANCEL_WAIT_S)
    return JobStatus(**job.as_dict())


@router.get(
    "/jobs/{job_id}/mesh",
    response_class=Response,
    responses={
        200: {"content": {t: {} for t in sorted(set(MEDIA_TYPES.values()))}, "description": "the mesh file"},
        404: {"model": ErrorBody},
        409: {"model": ErrorBody, "description": "the job is not done"},
        410: {"model": ErrorBody, "description": "the job's trajectories are no longer kept"},
    },
    dependencies=[Depends(single_valued_query)],
)
async def get_job_mesh(
    job_id: JobId,
    jobs: JobsDep,
    served: ServedModelDep,
    step: Annotated[int | None, Query(ge=0, description="state index; default: the final state")] = None,
    channel: Annotated[Channel, Query(description="mask or si")] = "si",
    format: Annotated[MeshFormat, Query(description="glb, ply, obj, stl or vtp")] = "glb",
) -> Response:
    """The simulator's surface coloured by the surrogate's signed distance from it (nm; glb/ply carry the
    colours)."""
    job = _job(jobs, job_id)
    sim, pred = job.artifacts.get("sim"), job.artifacts.get("pred")
    if job.status != "done":
        raise HTTPException(status_code=409, detail=f"job {job_id!r} is {job.status}: no mesh yet")
    if sim is None or pred is None:
        raise HTTPException(
            status_code=410,
            detail=f"the trajectories of job {job_id!r} are no longer kept (only the newest finished jobs' "
            "are): submit the simulation again",
        )
    last = sim.steps
    step = last if step is None else step
    if step > last:
        reject(("query", "step"), f"step = {step} is beyond this job's last state ({last})")
    ch = 0 if channel == "mask" else 1
    meta = {"job_id": job_id, "step": step, "channel": channel, "colour": "surrogate signed distance, nm"}
    scene = job.artifacts.get("scene") or served.scene  # the per-case scene of the job's feature
    data = await anyio.to_thread.run_sync(
        error_mesh, sim.state(step)[ch], pred.state(step)[ch], scene, format, meta
    )
    return Response(
        content=data,
        media_type=MEDIA_TYPES[format],
        headers={
            "Content-Disposition": f'attachment; filename="nemsim_job_{job_id}_step{step}_{channel}.{format}"'
        },
    )
