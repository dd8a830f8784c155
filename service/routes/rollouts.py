"""Rollouts, their surface meshes and their exports.

Exports of a cached rollout, by its id (404 once it left the cache, as for its meshes):

* `metrics.csv`: one row per state; columns `step`, `time [s]` and each profile metric in nm (the unit in
  the column name, so a spreadsheet keeps it; `neck_depth`: the row the neck is measured on), undefined
  values (`nemsim.geometry.profile`: the hole has not reached the row a width is measured on) as empty
  cells; `#` comment lines first name the model, the scene and the controls (a recipe adds one column per
  control instead), say what an empty cell and `neck_depth` mean and state the frame of reference
  (`nemsim.geometry.frame`: depths below the initial Si top, widths across the hole axis). Built on a
  worker thread without a gate: a few hundred rows cost less than a gate's bookkeeping.
* `trajectory.h5`: the states in the simulator's data-file layout (`nemsim.data.hdf5`, one case), so
  `nemsim.data.hdf5.open_trajectories` and every HDF5 tool read it (`_write_trajectory`); the root
  attributes `frame`, `x_nm`, `y_nm` and `z_nm` place the grid in the frame of the meshes. Decoding and
  compressing every state is real work: it waits at the mesh gate like a mesh export.
"""

from __future__ import annotations

import base64
import csv
import io
import json
import math
import time
import uuid
from collections.abc import Iterable, Iterator
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request
from fastapi.responses import Response, StreamingResponse
from starlette.concurrency import run_in_threadpool
from starlette.types import Receive, Scope, Send

from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS, transform
from nemsim.geometry.frame import FRAME, grid_axes_nm
from nemsim.inference import MEDIA_TYPES, Refused
from service.deps import (
    GatesDep,
    ServedModelDep,
    SettingsDep,
    feature_case,
    gated,
    reject,
    single_valued_query,
)
from service.inverse import rollout_intervals, rollout_trust
from service.memory import ResponseBudget
from service.openapi import ErrorBody
from service.scheduler import Gates
from service.schemas import (
    Channel,
    FieldsPayload,
    MeshFormat,
    MeshPayload,
    RolloutRequest,
    RolloutResponse,
    Timings,
    array_to_controls,
    json_response,
)
from service.served_model import RolloutResult, ServedModel, UnknownRollout

router = APIRouter(tags=["rollouts"])
UNDEFINED = "not defined at that step (the hole has not reached the row it is measured on)"  # empty / NaN


def _mesh_url(rollout_id: str, step: int, channel: str, fmt: str) -> str:
    return f"/rollouts/{rollout_id}/mesh?step={step}&channel={channel}&format={fmt}"


async def _mesh_bytes(
    request: Request,
    served: ServedModel,
    gates: Gates,
    result: RolloutResult,
    step: int,
    channel: str,
    fmt: str,
) -> bytes:
    cached = served.cached_mesh(result, step, channel, fmt)
    request.app.state.metrics.cache_lookup("mesh", cached is not None)
    if cached is not None:
        return cached
    try:
        return await gated(request, gates.mesh, served.mesh, result, step, channel, fmt)
    except ValueError as exc:  # e.g. no zero-level surface in this channel at this step
        reject(("query", "step"), f"no {channel} mesh at step {step}: {exc}")


def _fields_payload(served: ServedModel, result: RolloutResult, data: str) -> FieldsPayload:
    """The final state's field, or (`data` given: a placeholder for the stream) every state's."""
    steps = [result.steps] if not data else list(range(result.steps + 1))
    shape = [len(steps), *result.states.shape[1:]]
    if not data:
        state = result.states.take(steps).astype("<f2", copy=False)  # (1, 2, D, H, W)
        data = base64.b64encode(state.data.cast("B")).decode("ascii")  # the array's own buffer, no copy
    return FieldsPayload(  # type: ignore[call-arg]
        shape=shape, steps=steps, d_max_nm=float(served.scene.d_max_nm), data=data
    )


MESH_PIECE_BYTES = 3 << 18  # a mesh's bytes are base64-encoded this much at a time (a multiple of 3)


def _base64_pieces(chunks: Iterable[bytes]) -> Iterator[bytes]:
    """base64 of the chunks' bytes in sequence, piece by piece (whole 3-byte groups but for the last)."""
    carry = b""
    for chunk in chunks:
        raw = carry + chunk
        cut = len(raw) - len(raw) % 3
        carry = raw[cut:]
        yield base64.b64encode(memoryview(raw)[:cut])
    if carry:
        yield base64.b64encode(carry)


def _pieces(raw: bytes) -> Iterator[bytes]:
    view = memoryview(raw)
    for i in range(0, len(raw), MESH_PIECE_BYTES):
        yield bytes(view[i : i + MESH_PIECE_BYTES])


class _BudgetedStream(StreamingResponse):
    """A streamed body that hands its bytes back to the response budget once sent, failed or abandoned."""

    def __init__(self, content: Iterator[bytes], length: int, budget: ResponseBudget) -> None:
        super().__init__(content, media_type="application/json", headers={"Content-Length": str(length)})
        self.budget, self.length = budget, length

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.budget.release(self.length)


def _streamed(response: RolloutResponse, slots: dict[str, tuple[int, Iterable[bytes]]],
              budget: ResponseBudget) -> Response:
    """`response` with the data of its `slots` (placeholder -> (byte count, the bytes in chunks)) streamed
    as base64, chunk by chunk (the fields decoded state block by state block): every state of a trajectory
    is tens of MB of JSON, and building a body whole (arrays, base64, strings, JSON) took several times
    that at once per response. 503 + Retry-After when the body does not fit the response budget."""
    text = response.model_dump_json().encode()
    order = sorted(slots, key=lambda slot: text.index(f'"{slot}"'.encode()))
    length = len(text) - sum(len(slot) for slot in slots) + sum(4 * -(-slots[k][0] // 3) for k in slots)
    if not budget.reserve(length):
        raise HTTPException(
            status_code=503,
            detail=f"{budget.used >> 20} MB of large responses are being sent (the server's budget is "
            f"{budget.max_bytes >> 20} MB); retry shortly",
            headers={"Retry-After": "1"},
        )

    def body() -> Iterator[bytes]:
        rest = text
        for slot in order:
            head, rest = rest.split(f'"{slot}"'.encode(), 1)
            yield head + b'"'
            yield from _base64_pieces(slots[slot][1])
            rest = b'"' + rest
        yield rest

    # a plain iterator: Starlette runs each step in its thread pool, off the event loop
    return _BudgetedStream(body(), length, budget)


def cached_rollout(served: ServedModel, rollout_id: str) -> RolloutResult:
    """A rollout of the served model's cache by id; 404 when it was never computed here or was evicted."""
    try:
        return served.get_rollout(rollout_id)
    except UnknownRollout:
        raise HTTPException(
            status_code=404,
            detail=f"unknown rollout id {rollout_id!r} (never computed here, or evicted from "
            "the cache): POST /rollout again, it returns the same id",
        ) from None


@router.post("/rollout", response_model=RolloutResponse)
async def post_rollout(
    request: Request, body: RolloutRequest, served: ServedModelDep, settings: SettingsDep, gates: GatesDep
) -> Response:
    """Predict the etch over `steps` transitions of 0.1 s; metrics always, fields and meshes on demand."""
    t_start = time.perf_counter()
    assert body.steps is not None  # resolved by the request validator
    if body.steps > settings.max_steps:
        reject(
            ("body", "steps"), f"steps = {body.steps} exceeds this server's ceiling of {settings.max_steps}"
        )
    if len(body.meshes) > settings.max_meshes:
        reject(
            ("body", "meshes"),
            f"{len(body.meshes)} meshes requested; at most {settings.max_meshes} per rollout",
        )
    predictor = served.predictor
    case = await feature_case(served, body.geometry)
    try:
        schedule, warnings, found, clipped = predictor.check_range(body.schedule(), settings.extrapolation)
    except Refused as exc:
        reject(("body", body.source), str(exc))
    outside = predictor.geometry_outside(case.feature)
    if outside is not None:
        warnings.append(outside)
    if body.steps > predictor.horizon_steps:
        warnings.append(
            f"steps = {body.steps} goes beyond the {predictor.horizon_steps}-step horizon the model was "
            "trained on"
        )
    rid, hit = served.lookup_rollout(schedule, case)
    metrics = request.app.state.metrics
    metrics.cache_lookup("rollout", hit is not None)
    if hit is not None:
        result, cached = hit, True
    else:
        result, cached = await gated(request, gates.rollout, served.compute_rollout, schedule, rid, case)
        if not cached:
            metrics.rollout_computed(result.rollout_ms / 1e3)
    if result.non_finite_from is not None:  # NaN/Inf states are no answer (and no 5xx: nothing crashed)
        reject(
            ("body", body.source),
            f"the model's prediction for these controls is not finite (NaN/Inf) from step "
            f"{result.non_finite_from} on: no rollout can be returned",
        )
    warnings.extend(result.warnings)

    t0 = time.perf_counter()
    fields = None
    slot = f"fields-{uuid.uuid4().hex}" if body.fields == "all" else ""  # placeholder of the streamed data
    if body.fields != "none":  # decoding a state: off the event loop
        fields = await run_in_threadpool(_fields_payload, served, result, slot)
    t1 = time.perf_counter()
    meshes = []
    slots: dict[str, tuple[int, Iterable[bytes]]] = {}  # streamed data: placeholder -> (bytes, chunks)
    if slot:
        n_bytes = 2 * int(np.prod(result.states.shape))  # float16
        slots[slot] = (n_bytes, (b.astype("<f2", copy=False).tobytes() for b in result.states.blocks()))
    for spec in body.meshes:
        raw = await _mesh_bytes(request, served, gates, result, spec.step, spec.channel, spec.format)
        mesh_slot = f"mesh-{uuid.uuid4().hex}"
        slots[mesh_slot] = (len(raw), _pieces(raw))
        meshes.append(
            MeshPayload(
                step=spec.step,
                channel=spec.channel,
                format=spec.format,
                media_type=MEDIA_TYPES[spec.format],
                url=_mesh_url(result.id, spec.step, spec.channel, spec.format),
                data=mesh_slot,
            )
        )
    t2 = time.perf_counter()
    varying = body.recipe is not None
    response = RolloutResponse(
        id=result.id,
        model_id=result.model_id,
        steps=result.steps,
        cached=cached,
        times_s=result.times_s,
        metrics=result.metrics,
        controls=array_to_controls(result.controls_raw[0]),
        defaulted=body.defaulted,
        recipe=[array_to_controls(row) for row in result.controls_raw] if varying else None,
        geometry=result.geometry,
        warnings=warnings,
        extrapolation=[e.as_dict() for e in found],  # type: ignore[misc]
        clipped=clipped,
        fields=fields,
        meshes=meshes,
        intervals=rollout_intervals(served, result.metrics) if body.intervals else None,
        trust=rollout_trust(served, schedule.raw, schedule.normalized, case.feature),
        timings=Timings(
            total_ms=1e3 * (time.perf_counter() - t_start),
            rollout_ms=0.0 if cached else result.rollout_ms,
            metrics_ms=0.0 if cached else result.metrics_ms,
            fields_ms=1e3 * (t1 - t0),
            meshes_ms=1e3 * (t2 - t1),
        ),
    )
    if not slots:
        return json_response(response)
    return _streamed(response, slots, request.app.state.response_budget)


@router.get(
    "/rollouts/{rollout_id}/mesh",
    response_class=Response,
    responses={
        200: {"content": {t: {} for t in sorted(set(MEDIA_TYPES.values()))}, "description": "the mesh file"},
        404: {"model": ErrorBody, "description": "unknown or expired rollout id"},
    },
    dependencies=[Depends(single_valued_query)],
)
async def get_mesh(
    request: Request,
    rollout_id: Annotated[str, Path(max_length=64)],
    served: ServedModelDep,
    gates: GatesDep,
    step: Annotated[int | None, Query(ge=0, description="state index; default: the final state")] = None,
    channel: Annotated[Channel, Query(description="mask or si")] = "si",
    format: Annotated[MeshFormat, Query(description="glb, ply, obj, stl or vtp (VTK PolyData)")] = "glb",
) -> Response:
    """The zero-level surface of one channel at one step of a cached rollout, in nm, with provenance."""
    result = cached_rollout(served, rollout_id)
    step = result.steps if step is None else step
    if step > result.steps:
        reject(("query", "step"), f"step = {step} is beyond this rollout's last state ({result.steps})")
    data = await _mesh_bytes(request, served, gates, result, step, channel, format)
    filename = f"nemsim_{rollout_id}_step{step}_{channel}.{format}"
    return Response(
        content=data,
        media_type=MEDIA_TYPES[format],
        headers={
            "Content-Disposition": f'attachment; filename="{filename}"',
            "X-Model-Id": served.model_id,
        },
    )


def _number(value: float | None) -> str:
    """A CSV cell: six significant digits (far finer than the metrics' accuracy), empty when undefined."""
    return "" if value is None or not math.isfinite(value) else f"{value:.6g}"


def metrics_csv(served: ServedModel, result: RolloutResult) -> str:
    """The per-state profile metrics of a rollout as CSV text (module docstring)."""
    raw = result.controls_raw  # (T, 14) physical units
    varying = bool((raw != raw[0]).any())
    scene = served.scene
    out = io.StringIO()
    out.write(
        f"# NEMSim rollout {result.id}: model {result.model_id}, scene {scene.name} (voxel "
        f"{scene.voxel_nm:g} nm), {result.steps} transitions of {scene.snapshot_dt_s:g} s\n"
    )
    out.write(f"# geometry: {json.dumps(result.geometry)}\n")
    if varying:
        out.write(
            f"# controls: a recipe of {len(raw)} control sets; the row of step k >= 1 holds the controls of "
            "the transition into step k\n"
        )
    else:
        out.write(f"# controls (physical units): {json.dumps(array_to_controls(raw[0]))}\n")
    out.write(
        f"# empty cell: {UNDEFINED}; neck_depth: the row neck_width is measured on (the neck width jumps "
        "where the neck moves to another row)\n"
    )
    out.write(
        f"# frame: {FRAME}; depths (etch_depth, neck_depth) are below the initial Si top, widths across "
        "the hole axis\n"
    )
    names = list(result.metrics)
    header = ["step", "time [s]"] + [f"{n} [nm]" for n in names]
    if varying:
        header += [f"{s.name} [{s.unit}]" for s in CONTROL_SPECS]
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    for k, t in enumerate(result.times_s):
        row = [str(k), f"{t:.6g}"] + [_number(result.metrics[n][k]) for n in names]
        if varying:
            row += [repr(float(v)) for v in raw[k - 1]] if k else [""] * len(CONTROL_NAMES)
        writer.writerow(row)
    return out.getvalue()


def _write_trajectory(served: ServedModel, result: RolloutResult) -> bytes:
    """A rollout as an HDF5 file in the simulator's data-file layout (`nemsim.data.hdf5`), one case:
    `states` (1, T+1, 2, D, H, W) float16 normalized SDF (x `d_max` for nm), `times` (T+1,) s,
    `controls_raw` (1, 14) the first transition's controls and `controls_raw_schedule` (1, T, 14) every
    transition's, `case_ids` [0], `seeds` [-1] (no simulator seed), `complete` [1]; the root attributes
    of the data files (scene JSON, control and channel names, `d_max`, rules SHA-256, `generator`
    naming the model) plus `source`, `model_id`, `rollout_id`, `voxel_nm`, `controls` (JSON), `frame` and
    the voxel centres' coordinates in that frame, `x_nm` (W,), `y_nm` (H,), `z_nm` (D,). Extra:
    `metrics/<name>` (T+1,) nm, NaN where undefined (attribute `nan` says so). `check_dataset`'s data-set
    checks (T = the scene's horizon, controls inside the design ranges) may flag a rollout that differs from
    a simulated case."""
    import h5py

    from nemsim.data.hdf5 import CHANNEL_NAMES, DEFAULT_COMPRESSION, FORMAT_VERSION

    scene, loaded = result.scene, served.predictor.loaded  # the per-case scene: its feature and frame
    raw = np.asarray(result.controls_raw, dtype=np.float64)  # (T, 14)
    states_shape = (1, result.steps + 1, *scene.state_shape)
    provenance = {
        "source": "NEMSim surrogate rollout",
        "model_id": result.model_id,
        "checkpoint": loaded.path.name if loaded.path else "",
        "rollout_id": result.id,
    }
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.attrs.update(
            format_version=FORMAT_VERSION,
            scene=scene.to_json(),
            control_names=list(CONTROL_NAMES),
            channel_names=list(CHANNEL_NAMES),
            d_max=float(scene.d_max_nm),
            d_max_unit="nm",
            d_max_vox=float(scene.d_max_vox),
            rules_sha256=str(loaded.rules.sha256),
            generator=json.dumps(provenance, sort_keys=True),
            source="surrogate",
            model_id=result.model_id,
            rollout_id=result.id,
            voxel_nm=float(scene.voxel_nm),
            controls=json.dumps(array_to_controls(raw[0])),
            frame=FRAME,
            **{f"{axis}_nm": values for axis, values in grid_axes_nm(scene).items()},
        )
        filt, level, shuffle = DEFAULT_COMPRESSION
        states = f.create_dataset(
            "states", shape=states_shape, dtype="<f2", chunks=(1, 1, *scene.state_shape),
            compression=filt, compression_opts=level, shuffle=shuffle,
        )  # fmt: skip
        k = 0
        for block in result.states.blocks():  # (n, 2, D, H, W) float16, a few states at a time
            states[0, k : k + len(block)] = block
            k += len(block)
        f["times"] = np.asarray(result.times_s, dtype=np.float64)
        f["controls_raw"] = raw[:1]
        f["controls_transformed"] = transform(raw[:1])
        f["controls_raw_schedule"] = raw[None]
        f["case_ids"] = np.zeros(1, dtype=np.int64)
        f["seeds"] = np.full(1, -1, dtype=np.int64)
        f["complete"] = np.ones(1, dtype=np.uint8)
        f.create_dataset("case_meta", data=[json.dumps(provenance)], dtype=h5py.string_dtype())
        for name, values in result.metrics.items():
            f[f"metrics/{name}"] = np.array([np.nan if v is None else v for v in values], dtype=np.float64)
            f[f"metrics/{name}"].attrs.update(unit="nm", nan=UNDEFINED)
    return buf.getvalue()


_EXPORT_RESPONSES: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorBody, "description": "unknown or expired rollout id"},
}


def _attachment(data: bytes | str, media_type: str, filename: str, model_id: str) -> Response:
    return Response(
        content=data,
        media_type=media_type,
        headers={"Content-Disposition": f'attachment; filename="{filename}"', "X-Model-Id": model_id},
    )


@router.get(
    "/rollouts/{rollout_id}/metrics.csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}, "description": "the metrics table"}, **_EXPORT_RESPONSES},
)
async def get_metrics_csv(
    rollout_id: Annotated[str, Path(max_length=64)], served: ServedModelDep
) -> Response:
    """The profile metrics of a cached rollout, one row per state, as CSV (nm; empty cells: undefined)."""
    result = cached_rollout(served, rollout_id)
    text = await run_in_threadpool(metrics_csv, served, result)
    return _attachment(text, "text/csv", f"nemsim_{rollout_id}_metrics.csv", served.model_id)


@router.get(
    "/rollouts/{rollout_id}/trajectory.h5",
    response_class=Response,
    responses={
        200: {"content": {"application/x-hdf5": {}}, "description": "the trajectory file"},
        **_EXPORT_RESPONSES,
    },
)
async def get_trajectory_h5(
    request: Request, rollout_id: Annotated[str, Path(max_length=64)], served: ServedModelDep, gates: GatesDep
) -> Response:
    """Every state of a cached rollout (both channels) as HDF5 in the simulator's data-file layout."""
    result = cached_rollout(served, rollout_id)
    data = await gated(request, gates.mesh, _write_trajectory, served, result)
    return _attachment(data, "application/x-hdf5", f"nemsim_{rollout_id}_trajectory.h5", served.model_id)
