"""Request model of `POST /design` (inverse design) and the interval part of rollout responses.

The spec itself is validated by `nemsim.analysis.inverse.spec_from_dict` (one set of rules for the CLI and
the service); this model adds the request's own options and the JSON schema readers see.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from service.schemas import _json_integer

MetricName = Literal["etch_depth", "top_width", "bottom_width", "mask_loss", "bowing"]


class TargetValue(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    value: float = Field(description="target value, nm")
    tol: float | None = Field(
        None, gt=0, description="tolerance, nm (default: depth 5, widths 3, mask loss 2, bowing 2)"
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
        default_factory=dict, description="controls held at these values (physical units)"
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
        False, description="run the simulator on the top recipes and report achieved against target"
    )
    verify_top: Annotated[int, Field(ge=1, le=3), BeforeValidator(_json_integer)] | None = Field(
        None, description="recipes to simulate with verify (default 1; with refine 2, the round-0 recipes)"
    )
    refine: bool | None = Field(
        None,
        description="simulator-corrected design (implies verify): when the top recipes miss in the "
        "simulator, the simulator-minus-surrogate offset at the best one shifts the targets and a local "
        "search around it proposes a new recipe for the simulator, round after round; the top recipe is "
        "then the best simulated one (`verified_by`), and `refinement` reports every round. Default: on "
        "when verify is true (false: only simulate the top recipes)",
    )
    refine_rounds: Annotated[int, Field(ge=0, le=3), BeforeValidator(_json_integer)] | None = Field(
        None, description="simulator-corrected rounds at most (default 2; the job stops within about 60 s)"
    )
    sim_seed: Annotated[int, Field(ge=0, le=2**63 - 1), BeforeValidator(_json_integer)] = Field(
        1, description="simulator seed of the verification runs"
    )

    def spec_dict(self) -> dict[str, Any]:
        """The spec part in `nemsim.analysis.inverse.spec_from_dict`'s form."""
        targets = {
            k: (v if isinstance(v, float | int) else {"value": v.value, **({"tol": v.tol} if v.tol else {})})
            for k, v in self.targets.items()
        }
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
