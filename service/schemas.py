"""Request and response models of the service, split by direction (STYLE rule 13).

Controls are given by name in physical units; each field's JSON schema carries its unit, the
physically admissible range (violations are 422 naming the field) and the design range the model
was trained on (values outside it are accepted with a warning). The field set is built from
`nemsim.controls.CONTROL_SPECS`, so units and ranges are typed once.

A control set may be partial: a missing control takes the documented default (the centre of the design
range, `default_controls_raw`, what `/model` lists), and the answer names the defaulted ones, so an
engineer changes two knobs without copying fourteen. An unknown name is refused (a typo must not
silently become a default) with the closest valid name (`nemsim.controls.unknown_control`). Both rules
live in the `Controls` model only, so rollouts, recipes and simulator jobs share them.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    create_model,
    model_validator,
)
from starlette.responses import Response

from nemsim.controls import (
    CONTROL_NAMES,
    CONTROL_SPECS,
    GUARD_MAX,
    check_control,
    check_controls,
    from_normalized,
    guard_max,
    to_normalized,
    unknown_control,
)
from nemsim.inference import ControlSchedule

DEFAULT_STEPS = 100  # the paper horizon: 100 transitions of 0.1 s
MAX_STEPS_HARD = 10_000  # no configuration may allow more (Settings.max_steps has the same bound)
CHANNELS = ("mask", "si")  # state channel 0, 1
Channel = Literal["mask", "si"]
FeatureKind = Literal["hole", "trench"]
GEOMETRY_MAX_NM = 10_000.0  # a schema bound far past any grid (the fit to the scene is the route's check)
MeshFormat = Literal["glb", "ply", "obj", "stl", "vtp"]
FieldsMode = Literal["none", "final", "all"]

_STRICT = ConfigDict(extra="forbid", allow_inf_nan=False)


def _json_integer(value: Any) -> Any:
    """JSON Schema's integer: a number with no fractional part (3 and 3.0), never a string or boolean."""
    if isinstance(value, bool | str):
        raise ValueError("must be a JSON integer (a number, not a string or boolean)")
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _admissible(spec: Any):
    """After-validator: `nemsim.controls.check_control`, the rules `/design` and the CLI apply too
    (physically impossible values, values past the scale guard, fractional exponents), naming the control."""

    def check(value: float) -> float:
        return check_control(spec.name, value)

    return check


def check_scale(raw: np.ndarray, where: str) -> None:
    """Raise ValueError naming the first inadmissible control of raw (..., 14) (`check_controls`)."""
    check_controls(raw, where)


def default_controls_raw() -> np.ndarray:
    """The documented default base control vector: the centre of the design range in normalized
    coordinates (geometric mean for log-sampled fluxes), integer controls rounded. (14,) physical units."""
    raw = np.asarray(from_normalized(np.zeros(len(CONTROL_NAMES))), dtype=np.float64)
    for i, spec in enumerate(CONTROL_SPECS):
        if spec.kind == "int":
            raw[i] = float(round(raw[i]))
    return raw


def _control_field(spec: Any, default: float | None, *, strict: bool = True) -> tuple[Any, Any]:
    """strict: JSON numbers only (no strings, no booleans); query parameters arrive as text (strict=False)."""
    extra: dict[str, Any] = {
        "unit": spec.unit,
        "kind": spec.kind,
        "train_min": spec.low,
        "train_max": spec.high,
    }
    if math.isfinite(spec.phys_min):
        extra["minimum"] = spec.phys_min
    extra["maximum"] = min(spec.phys_max, guard_max(spec.name))
    if spec.kind == "int":
        extra["multipleOf"] = 1
    what = "integer cosine-power exponent" if spec.kind == "int" else spec.kind + "-sampled"
    description = (
        f"{spec.name} in {spec.unit} ({what}); trained on {spec.low:g}..{spec.high:g}; "
        f"physically admissible {spec.phys_min:g}..{spec.phys_max:g}; accepted up to "
        f"{guard_max(spec.name):g}" + ("; whole numbers only" if spec.kind == "int" else "")
    )
    typ = Annotated[float, Field(strict=strict), AfterValidator(_admissible(spec))]
    example = float(default_controls_raw()[CONTROL_NAMES.index(spec.name)])
    field = Field(
        ... if default is None else default,
        description=description,
        json_schema_extra=extra,
        examples=[example],
    )
    return (typ, field)


_DEFAULTS = default_controls_raw()


def refuse_unknown_names(data: Any, extra: tuple[str, ...] = ()) -> Any:
    """Before-validator of a control set: ValueError for the first name that is neither a control nor one
    of `extra`, naming the closest valid name (an unknown name is never dropped or defaulted)."""
    if isinstance(data, dict):
        for name in data:
            if name not in CONTROL_NAMES and name not in extra:
                raise ValueError(unknown_control(str(name), extra))
    return data


class _ControlsBase(BaseModel):
    model_config = _STRICT

    @model_validator(mode="before")
    @classmethod
    def _known_names(cls, data: Any) -> Any:
        return refuse_unknown_names(data)


Controls = create_model(  # type: ignore[call-overload]
    "Controls",
    __base__=_ControlsBase,
    __doc__="The 14 process controls by name, in physical units. Any subset: a missing control takes its "
    "documented default (the centre of the design range, as listed by GET /model); an unknown name is "
    "refused with the closest valid one.",
    **{s.name: _control_field(s, float(_DEFAULTS[i])) for i, s in enumerate(CONTROL_SPECS)},
)


class _MechanismsBase(BaseModel):
    model_config = _STRICT

    @model_validator(mode="before")
    @classmethod
    def _known_names(cls, data: Any) -> Any:
        return refuse_unknown_names(data, extra=("factors",))

    @model_validator(mode="after")
    def _meaningful(self) -> _MechanismsBase:
        check_scale(np.array([getattr(self, n) for n in CONTROL_NAMES]), "")
        return self


def _split_commas(value: Any) -> Any:
    """`factors=0.5,2` and `factors=0.5&factors=2` mean the same list."""
    if isinstance(value, str):
        value = [value]
    if isinstance(value, list):
        return [part.strip() for v in value for part in (v.split(",") if isinstance(v, str) else [v])]
    return value


MechanismsQuery = create_model(  # type: ignore[call-overload]
    "MechanismsQuery",
    __base__=_MechanismsBase,
    __doc__="A base control vector by name in physical units; missing controls take the documented default "
    "(centre of the design range, geometric mean for fluxes).",
    factors=(
        Annotated[
            list[Annotated[float, Field(gt=0, le=100)]],
            Field(min_length=1, max_length=4),
            BeforeValidator(_split_commas),
        ]
        | None,
        Field(
            None,
            description="flux multiplier levels for Cl+ and neutral Cl (> 0, at most 4); the "
            "interventions are all (s_Cl+, s_Cl) pairs of these levels and 1 except (1, 1). "
            "Give them repeated (factors=0.5&factors=2) or comma-separated (factors=0.5,2). "
            "Default: 0.5 and 1.5 (the eight of the paper). Every other parameter may appear once",
        ),
    ),
    **{s.name: _control_field(s, float(_DEFAULTS[i]), strict=False) for i, s in enumerate(CONTROL_SPECS)},
)


def controls_to_array(controls: BaseModel) -> np.ndarray:
    """(14,) float64 in CONTROL_NAMES order."""
    return np.array([getattr(controls, n) for n in CONTROL_NAMES], dtype=np.float64)


def array_to_controls(raw: np.ndarray) -> dict[str, float]:
    return {n: float(v) for n, v in zip(CONTROL_NAMES, raw, strict=True)}


# --- requests --------------------------------------------------------------------------------------


class Geometry(BaseModel):
    """The feature etched (nemsim.geometry.feature.Feature): left out, the model's own (GET /model,
    `geometry.default`). It must fit the scene's grid (else 422 saying the accepted range); a kind the model
    was not trained on is refused (422), cd or mask outside the trained ranges is answered with a `reject`
    trust verdict."""

    model_config = _STRICT
    kind: FeatureKind = Field(description="hole (a cylinder) or trench (a line along y)")
    cd_nm: float = Field(
        gt=0, le=GEOMETRY_MAX_NM, strict=True,
        description="opening, nm: the hole's diameter or the trench's width",
    )
    mask_nm: float = Field(
        gt=0, le=GEOMETRY_MAX_NM, strict=True,
        description="mask (resist) thickness, nm; built in whole voxels (the answer echoes what was built)",
    )

    def feature(self) -> Any:
        """The library's Feature (nemsim.geometry.feature)."""
        from nemsim.geometry.feature import Feature

        return Feature(self.kind, float(self.cd_nm), float(self.mask_nm))


GEOMETRY_FIELD_DESCRIPTION = (
    "the feature etched (kind, cd_nm, mask_nm); default: the model's own (GET /model)"
)


class MeshSpec(BaseModel):
    """One surface mesh to return inline with a rollout."""

    model_config = _STRICT
    step: Annotated[int, Field(ge=0, le=MAX_STEPS_HARD), BeforeValidator(_json_integer)] = Field(
        description="state index, 0 = initial geometry, `steps` = final (at most `steps`)"
    )
    channel: Channel = Field("si", description="mask (resist) or si (silicon)")
    format: MeshFormat = Field("glb", description="file format of the mesh")


def _normalized_bounds() -> tuple[np.ndarray, np.ndarray]:
    """(14,) lowest and highest accepted normalized value per control: the images of the physical
    minimum (0) and of the scale guard (`guard_max`). Normalized input is checked against these
    directly, so the schema and the server agree to the last bit."""
    with np.errstate(divide="ignore"):
        lo = np.asarray(to_normalized(np.array([s.phys_min for s in CONTROL_SPECS], dtype=np.float64)))
    hi = np.asarray(to_normalized(GUARD_MAX.copy()))
    return lo, hi


NORM_MIN, NORM_MAX = _normalized_bounds()

NormalizedVector = Annotated[
    list[Annotated[float, Field(strict=True)]],
    Field(
        min_length=len(CONTROL_NAMES),
        max_length=len(CONTROL_NAMES),
        json_schema_extra={
            "prefixItems": [
                {"type": "number", "minimum": float(lo), "maximum": float(hi), "title": n}
                for n, lo, hi in zip(CONTROL_NAMES, NORM_MIN, NORM_MAX, strict=True)
            ]
        },
    ),
]


def _request_schema_extra(schema: dict[str, Any]) -> None:
    """Examples (a full and a partial control set), and "exactly one of controls, controls_normalized, recipe"
    (null counts as absent)."""
    schema["examples"] = [
        {"controls": array_to_controls(default_controls_raw()), "steps": 100},
        {"controls": {"flux_cl": 0.01, "energy_mean_ar_plus": 300.0}, "steps": 50},
    ]
    schema["oneOf"] = [
        {"required": [name], "properties": {name: {"not": {"type": "null"}}}}
        for name in ("controls", "controls_normalized", "recipe")
    ]


class ControlSource(BaseModel):
    """The controls of a run: exactly one of `controls` (physical units), `controls_normalized` or `recipe`,
    and `steps`. Shared by rollouts and simulator jobs, so both validate their controls the same way."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra=_request_schema_extra,
    )

    controls: Controls | None = Field(  # type: ignore[valid-type]
        None, description="constant controls by name, physical units (any subset; the rest take the defaults)"
    )
    controls_normalized: NormalizedVector | None = Field(
        None,
        description=f"constant controls as 14 normalized numbers in the order {list(CONTROL_NAMES)}; "
        "[-1, 1] is the training range (outside it: a warning)",
    )
    recipe: list[Controls] | None = Field(  # type: ignore[valid-type]
        None,
        min_length=1,
        max_length=MAX_STEPS_HARD,
        description="one control set per transition (time-varying process); `steps`, when given too, must "
        "be its length",
    )
    steps: Annotated[int, Field(ge=1, le=MAX_STEPS_HARD), BeforeValidator(_json_integer)] | None = Field(
        None,
        description=f"transitions of 0.1 s to predict; 1..{DEFAULT_STEPS} by default (server ceiling "
        f"NEMSIM_MAX_STEPS); default {DEFAULT_STEPS}, or the recipe length",
    )
    geometry: Geometry | None = Field(None, description=GEOMETRY_FIELD_DESCRIPTION)

    @model_validator(mode="after")
    def _one_source(self) -> ControlSource:
        given = [n for n in ("controls", "controls_normalized", "recipe") if getattr(self, n) is not None]
        if len(given) != 1:
            raise ValueError(
                "give exactly one of controls (by name, physical units), controls_normalized (14 numbers) "
                f"or recipe (one control set per transition); got {given or 'none'}"
            )
        if self.recipe is not None:
            if self.steps is None:
                self.steps = len(self.recipe)
            elif self.steps != len(self.recipe):
                raise ValueError(
                    f"recipe has {len(self.recipe)} control sets but steps={self.steps}: "
                    "give one per transition"
                )
        if self.steps is None:
            self.steps = DEFAULT_STEPS
        if self.controls_normalized is not None:
            for i, spec in enumerate(CONTROL_SPECS):
                v = self.controls_normalized[i]
                if not NORM_MIN[i] <= v <= NORM_MAX[i]:
                    what = "physically impossible" if v < NORM_MIN[i] else "far outside any meaningful range"
                    raise ValueError(
                        f"controls_normalized[{i}] ({spec.name}) = {v:g} is {what}: accepted "
                        f"{NORM_MIN[i]:.6g}..{NORM_MAX[i]:.6g} ({spec.phys_min:g}..{guard_max(spec.name):g} "
                        f"{spec.unit})"
                    )
        else:
            check_scale(self._rows_raw(), "")
        return self

    def _rows_raw(self) -> np.ndarray:
        """(K, 14) the distinct control rows given in physical units (K = recipe length, else 1)."""
        if self.recipe is not None:
            return np.stack([controls_to_array(c) for c in self.recipe])
        assert self.controls is not None  # one source is given (validator); normalized input has no rows
        return controls_to_array(self.controls)[None]

    def schedule(self) -> ControlSchedule:
        """The controls per transition in both forms, normalized once (normalized input is kept as given)."""
        assert self.steps is not None  # set by the validator
        if self.controls_normalized is not None:
            return ControlSchedule.from_normalized(self.controls_normalized, self.steps)
        rows = self._rows_raw()  # (K, 14)
        per_transition = rows if self.recipe is not None else np.repeat(rows, self.steps, axis=0)  # (T, 14)
        return ControlSchedule.physical(per_transition)

    @property
    def defaulted(self) -> list[str]:
        """The controls left out of the request and filled from the defaults (CONTROL_NAMES order); for a
        recipe, those left out of any of its control sets; none for `controls_normalized` (all 14 given)."""
        rows: list[BaseModel] = [self.controls] if self.controls is not None else self.recipe or []
        given = set.intersection(*(row.model_fields_set for row in rows)) if rows else set(CONTROL_NAMES)
        return [n for n in CONTROL_NAMES if n not in given]

    @property
    def source(self) -> str:
        """Which of controls, controls_normalized, recipe was given."""
        return next(n for n in ("controls", "controls_normalized", "recipe") if getattr(self, n) is not None)


class RolloutRequest(ControlSource):
    """Give exactly one of `controls` (physical units), `controls_normalized` or `recipe`."""

    fields: FieldsMode = Field(
        "none", description="SDF fields to return: none, the final state, or all states (float16, base64)"
    )
    meshes: list[MeshSpec] = Field(
        default_factory=list,
        max_length=64,
        description="surface meshes to return inline (server limit applies); each `step` at most the "
        "rollout's steps (`steps`, the recipe's length, else the default)",
    )
    intervals: bool = Field(
        False, strict=True, description="add per-step conformal intervals of the profile metrics (true/false)"
    )

    @model_validator(mode="after")
    def _meshes_in_range(self) -> RolloutRequest:
        assert self.steps is not None  # resolved by ControlSource._one_source
        for k, mesh in enumerate(self.meshes):
            if mesh.step > self.steps:
                raise ValueError(
                    f"meshes[{k}].step = {mesh.step} is beyond the last state (steps = {self.steps})"
                )
        return self


class SimulationRequest(ControlSource):
    """A simulator run of the loaded checkpoint's scene for the same controls a rollout takes."""

    seed: Annotated[int, Field(ge=0, le=2**63 - 1), BeforeValidator(_json_integer)] = Field(
        1, description="simulator seed (np.random.default_rng(seed)); the same seed gives the same run"
    )


class JobCreated(BaseModel):
    id: str
    kind: str
    status: str
    location: str = Field(description="GET this for the job's status and result")
    controls: dict[str, float] | None = Field(
        default=None,
        description="a simulation's controls, every one of them (the first transition's for a recipe)",
    )
    defaulted: list[str] = Field(
        default_factory=list, description="controls the request left out, taken from the defaults"
    )
    geometry: dict[str, Any] | None = Field(
        None, description="the feature the job runs on, as built on the grid ({kind, cd_nm, mask_nm})"
    )


class JobStatus(BaseModel):
    id: str
    kind: str
    status: Literal["pending", "running", "done", "failed", "cancelled"] = Field(
        description="cancelled: stopped by DELETE /jobs/{id} (or the server stopping) and kept, without a "
        "result, until forgotten like a finished job (NEMSIM_JOBS_KEEP_S, NEMSIM_JOBS_KEEP_MAX; then 404); "
        "DELETE of a finished job leaves it unchanged"
    )
    progress: float = Field(ge=0.0, le=1.0)
    phase: str | None = Field(
        None,
        description="what the job is doing now: 'waiting in the queue', then as it runs (a design: loading "
        "the model, screening k/n recipes, the search's steps, 'simulator run k of n'); null once finished",
    )
    created: float = Field(description="creation time, seconds since the epoch")
    result: dict[str, Any] | None = Field(None, description="present when done")
    message: str | None = Field(None, description="why the job failed (one line)")


# --- responses -------------------------------------------------------------------------------------


class FieldsPayload(BaseModel):
    """SDF states, normalized (SDF / d_max, clipped to [-1, 1]; negative inside material)."""

    encoding: Literal["base64"] = "base64"
    dtype: Literal["<f2"] = Field("<f2", description="little-endian float16")
    order: Literal["C"] = "C"
    shape: list[int] = Field(description="(n_states, 2, D, H, W); channel 0 = mask, 1 = si; depth = z + 1")
    steps: list[int] = Field(description="state index of each entry along the first axis")
    channels: list[str] = list(CHANNELS)
    d_max_nm: float
    data: str


class MeshPayload(BaseModel):
    step: int
    channel: Channel
    format: MeshFormat
    media_type: str
    url: str = Field(description="GET this for the same file")
    data: str = Field(description="base64 of the file bytes")


class Timings(BaseModel):
    total_ms: float
    rollout_ms: float = Field(description="model rollout (0 when served from the cache)")
    metrics_ms: float
    fields_ms: float
    meshes_ms: float


class ExtrapolationInfo(BaseModel):
    """One control outside the training box (worst value over the transitions)."""

    control: str
    value: float = Field(description="the value given, physical units")
    unit: str
    train_min: float
    train_max: float
    side: Literal["below", "above"]
    half_widths_outside: float = Field(
        description="distance past the nearest edge of the box, in box half-widths, in the coordinate the "
        "model sees (log10 for fluxes)"
    )
    network_half_widths_outside: float | None = Field(
        None,
        description="where the network reads this control, in box half-widths past the edge: a model with "
        "control saturation holds far controls near the box (the ion-flux gate uses the value given); "
        "null: it reads the value as given",
    )


class RolloutResponse(BaseModel):
    id: str = Field(description="rollout id, for GET /rollouts/{id}/mesh")
    model_id: str
    steps: int
    cached: bool = Field(description="served from the cache (nothing recomputed)")
    times_s: list[float] = Field(description="time of each state, s (index = step)")
    metric_units: Literal["nm"] = "nm"
    metrics: dict[str, list[float | None]] = Field(
        description="profile metrics per state (index = step): etch depth, widths, bowing, mask loss"
    )
    controls: dict[str, float] = Field(
        description="the full control set of the first transition as used, physical units (defaults "
        "filled in)"
    )
    defaulted: list[str] = Field(
        [], description="controls the request left out, filled from the documented defaults (GET /model)"
    )
    recipe: list[dict[str, float]] | None = Field(None, description="per-transition controls, when varying")
    geometry: dict[str, Any] = Field(
        description="the feature rolled out, as built on the grid ({kind, cd_nm, mask_nm}; the mask in whole "
        "voxels)"
    )
    warnings: list[str]
    extrapolation: list[ExtrapolationInfo] = Field(
        [], description="controls outside the training box, as given (see the server's extrapolation policy)"
    )
    clipped: bool = Field(False, description="controls were clipped to the training box (policy 'clip')")
    fields: FieldsPayload | None = None
    meshes: list[MeshPayload] = []
    intervals: dict[str, Any] | None = Field(None, description="with intervals: per-step conformal intervals")
    trust: dict[str, Any] | None = Field(
        None,
        description="where the recipe lies (group of the extrapolation benchmark: in-box, corner, zero-flux, "
        "axis 1.5, axis 2, angle, beyond; its distance past the box and to the nearest training case), the "
        "error the benchmark measured there and a verdict level ok / warn / reject; `geometry`: whether the "
        "feature lies in the trained ranges (outside: level reject, whatever the controls)",
    )
    timings: Timings


class SlicesResponse(BaseModel):
    """Cross-sections through the hole axis of every state: bytes q = round((sdf + 1) * 127.5)."""

    encoding: Literal["base64"] = "base64"
    dtype: Literal["u1"] = "u1"
    shape: list[int] = Field(description="(n_states, 2, D, W); channel 0 = mask, 1 = si; depth = z + 1")
    voxel_nm: float
    d_max_nm: float
    data: str


class ControlInfo(BaseModel):
    name: str
    unit: str
    kind: str
    min: float | None = Field(description="physically admissible minimum (null: unbounded)")
    max: float | None = Field(description="physically admissible maximum (null: unbounded)")
    train_min: float
    train_max: float
    label: str = Field("", description="symbol")
    description: str = Field("", description="what the control means (one line)")
    default: float | None = Field(None, description="the documented default (centre of the design range)")


class ModelInfo(BaseModel):
    model_id: str
    checkpoint: str
    model_name: str
    n_params: int
    scene: dict[str, Any]
    rules_sha256: str
    max_steps: int
    horizon_steps: int
    summary: dict[str, Any]
    metrics: dict[str, Any]
    controls: list[ControlInfo]
    initial_state: str = Field(
        description="how the rollouts' initial state was built (simulator configuration)"
    )
    extrapolation: str = Field(
        description="policy for controls outside the training box: allow, clip or refuse"
    )
    geometry: dict[str, Any] = Field(
        description="the features: `default` (the model's own, used when a request gives none), `kinds` "
        "(per kind the model was trained on, the trained cd_nm and mask_nm ranges [low, high]; another kind "
        "is refused) and `source` (where the ranges come from)"
    )
    runtime: dict[str, Any] = Field(
        description="what rolls out: backend, precision (and, for openvino, the precision its CPU plugin "
        "runs), threads, fallback_reason, precision_requested (auto: the CPU's default), the CPU's name, "
        "its bfloat16 flags and its default precision"
    )


class MechanismsRequest(BaseModel):
    """A base control vector (any subset by name; the rest take the defaults), flux levels and a feature."""

    model_config = _STRICT
    controls: Controls = Field(  # type: ignore[valid-type]
        default_factory=lambda: Controls(),
        description="the base controls by name, physical units (any subset; the rest take the defaults)",
    )
    factors: list[Annotated[float, Field(gt=0, le=100, strict=True)]] | None = Field(
        None, min_length=1, max_length=4,
        description="flux multiplier levels for Cl+ and neutral Cl (as GET /mechanisms' `factors`)",
    )
    geometry: Geometry | None = Field(None, description=GEOMETRY_FIELD_DESCRIPTION)

    @model_validator(mode="after")
    def _meaningful(self) -> MechanismsRequest:
        check_scale(controls_to_array(self.controls)[None], "")
        return self


class MechanismsResponse(BaseModel):
    model_id: str
    controls: dict[str, float] = Field(description="the base control vector used, physical units")
    geometry: dict[str, Any] | None = Field(None, description="the feature analysed, as built on the grid")
    result: dict[str, Any] = Field(
        description="nemsim.analysis.counterfactual.mechanism_response: the Cl+/Cl interventions with "
        "Delta M per family (physical, chemical, coupled) and Delta R, base intensities lambda and "
        "attributions alpha"
    )
    warnings: list[str]
    extrapolation: list[ExtrapolationInfo] = []
    clipped: bool = False


class Health(BaseModel):
    status: str
    detail: str | None = None
    model_id: str | None = None
    message: str | None = Field(None, description="one readable line when not ready (the error shape)")


def json_response(model: BaseModel, status_code: int = 200) -> Response:
    """`model` as a JSON response, serialized by pydantic-core in one pass. A route returning this skips
    FastAPI's re-validation and encoding of its `response_model` (which stays the documented schema):
    the cheap routes answer on the event loop, so every millisecond there is a millisecond every other
    request waits."""
    return Response(model.model_dump_json(), status_code=status_code, media_type="application/json")


def jsonable(value: Any) -> Any:
    """Numpy/torch values to plain JSON; non-finite floats become None (JSON has no NaN)."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return _finite_or_none(value)
    if value is None or isinstance(value, bool | int | str):
        return value
    return str(value)
