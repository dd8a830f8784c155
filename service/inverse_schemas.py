"""Request model of `POST /design` (inverse design) and the interval part of rollout responses.

The spec is validated by the library's rules (`nemsim.analysis.inverse`: `check_target`, `check_tolerance`,
`check_fixed`, `check_bounds`; the held controls by `nemsim.controls.check_control`, as `/rollout`'s), one
set of rules for the CLI and the service: the validators below call them, so bad input is a 422 naming the
field; the route then checks the targets against the served model's scene (`check_targets`). This model
adds the request's own options and the JSON schema readers see.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, field_validator

from nemsim.analysis.inverse import MIN_TOL_NM, check_bounds, check_fixed, check_target, check_tolerance
from service.schemas import GEOMETRY_FIELD_DESCRIPTION, Geometry, _json_integer

MetricName = Literal["etch_depth", "top_width", "bottom_width", "mask_loss", "bowing"]


class TargetValue(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    value: float = Field(
        description="target value, nm: from 0 to the Si thickness (depth), the domain width (widths, "
        "bowing) or the mask thickness (mask loss) of the model's scene",
        json_schema_extra={"minimum": 0},
    )
    tol: float | None = Field(
        None,
        description=f"tolerance, nm, at least {MIN_TOL_NM:g} and at most the metric's range (default: depth "
        "5, widths 3, mask loss 2, bowing 2)",
        json_schema_extra={"minimum": MIN_TOL_NM},
    )


class Secondary(BaseModel):
    model_config = ConfigDict(extra="forbid")
    metric: MetricName
    goal: Literal["min", "max"] = "min"


class DesignRequest(BaseModel):
    """Targets on profile metrics at a step; the search returns `k` ranked recipes."""

    model_config = ConfigDict(
        extra="forbid",
        allow_inf_nan=False,
        json_schema_extra={
            "examples": [
                {
                    "targets": {
                        "etch_depth": {"value": 100, "tol": 5},
                        "bottom_width": {"value": 30, "tol": 3},
                    },
                    "secondary": {"metric": "mask_loss", "goal": "min"},
                    "k": 3,
                    "verify": True,
                }
            ]
        },
    )

    targets: dict[MetricName, TargetValue | float] = Field(
        min_length=1,
        description="target per metric (any subset), nm; a bare number takes the default tolerance",
    )
    step: Annotated[int, Field(ge=1, le=10_000), BeforeValidator(_json_integer)] | None = Field(
        None, description="state index the targets refer to (default: the model's horizon, 100 = 10 s)"
    )
    fixed: dict[str, float] = Field(
        default_factory=dict,
        description="controls held at these values (physical units; the ranges `/rollout` accepts)",
    )
    bounds: dict[str, tuple[float, float]] = Field(
        default_factory=dict,
        description="[low, high] per control in physical units (default: the training box)",
    )
    secondary: Secondary | None = Field(None, description="optional goal among recipes that meet the targets")
    k: Annotated[int, Field(ge=1, le=10), BeforeValidator(_json_integer)] = Field(
        3, description="recipes reported"
    )
    seed: Annotated[int, Field(ge=0, le=2**31 - 1), BeforeValidator(_json_integer)] = Field(
        0, description="search seed"
    )
    verify: bool = Field(
        False,
        strict=True,
        description="run the simulator on the top recipes and report achieved against target (true/false)",
    )
    verify_top: Annotated[int, Field(ge=1, le=3), BeforeValidator(_json_integer)] | None = Field(
        None,
        description="recipes to simulate with verify (default 1; with refine the round-0 recipes, default 1)",
    )
    refine: bool | None = Field(
        None,
        strict=True,
        description="simulator-corrected design (implies verify): when the top recipes miss in the "
        "simulator, the simulator-minus-surrogate offset at the best one shifts the targets and a local "
        "search around it proposes a new recipe for the simulator, round after round; the top recipe is "
        "then the best simulated one (`verified_by`), and `refinement` reports every round. A recipe that "
        "meets the targets in its run is confirmed by an independent run (seed sim_seed + 1) before it is "
        "the answer (`status` verified), as the design-cost benchmark measures it; the round-0 recipe, "
        "predicted to meet them before any run, runs with that seed straight away (a claim, `claimed`). "
        "Every run counts in `simulator_calls`. Default: on when verify is true (false: only simulate the "
        "top recipes)",
    )
    refine_rounds: Annotated[int, Field(ge=0, le=5), BeforeValidator(_json_integer)] | None = Field(
        None,
        description="simulator-corrected rounds at most (default 5; the job stops within about 60 s and "
        "after 8 simulator runs)",
    )
    sim_seed: Annotated[int, Field(ge=0, le=2**63 - 1), BeforeValidator(_json_integer)] = Field(
        1, description="simulator seed of the verification runs (a refined design's confirmations: + 1)"
    )
    geometry: Geometry | None = Field(
        None, description=GEOMETRY_FIELD_DESCRIPTION + "; the recipe is searched for this feature"
    )

    @field_validator("targets")
    @classmethod
    def _targets(cls, targets: dict[str, TargetValue | float]) -> dict[str, TargetValue | float]:
        for name, t in targets.items():
            if isinstance(t, TargetValue):
                check_target(name, t.value, where=f"targets.{name}.value")
                if t.tol is not None:
                    check_tolerance(name, t.tol)
            else:
                check_target(name, t)
        return targets

    @field_validator("fixed")
    @classmethod
    def _fixed(cls, fixed: dict[str, float]) -> dict[str, float]:
        check_fixed(fixed)
        return fixed

    @field_validator("bounds")
    @classmethod
    def _bounds(cls, bounds: dict[str, tuple[float, float]]) -> dict[str, tuple[float, float]]:
        check_bounds(bounds)
        return bounds

    def spec_dict(self) -> dict[str, Any]:
        """The spec part in `nemsim.analysis.inverse.spec_from_dict`'s form."""
        targets: dict[str, Any] = {}
        for k, v in self.targets.items():
            if isinstance(v, TargetValue):
                targets[k] = {"value": v.value} if v.tol is None else {"value": v.value, "tol": v.tol}
            else:
                targets[k] = v
        out: dict[str, Any] = {
            "targets": targets,
            "fixed": self.fixed,
            "bounds": {k: list(v) for k, v in self.bounds.items()},
            "k": self.k,
        }
        if self.step is not None:
            out["step"] = self.step
        if self.secondary is not None:
            out["secondary"] = self.secondary.model_dump()
        return out
