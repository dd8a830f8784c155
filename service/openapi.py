"""The OpenAPI document states the rules the server enforces: every request the server accepts is valid
under it, and a valid request is refused only for one of the two cross-field rules below.

Static rules live in the models (`service.schemas`: the scale guard as `maximum`, whole-number
exponents as `multipleOf`, "exactly one of" as `oneOf`, normalized bounds as `prefixItems`). What
depends on this server's settings (the `steps` ceiling, inline meshes per rollout) is written into
the document when it is first generated. Error responses share one schema (`ErrorBody`).

Two rules tie fields of a rollout request together: a recipe of n control sets means `steps` = n (when
`steps` is given too), and an inline mesh's `step` must not exceed the rollout's steps (the given
`steps`, the recipe's length, else the default 100). JSON Schema can state them only as one conditional
clause per possible n, which schema-driven tools (schemathesis) cannot expand at the default ceiling of
100 steps, so the request schema stays plain and the field descriptions carry these two rules; the server
refuses a request that breaks one with a 422 naming the field.

`/docs` is Swagger UI from the files vendored under `static/vendor/swagger-ui` (no CDN), so the reference
works without a network, as the page does.
"""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse
from pydantic import BaseModel, Field

from service.schemas import DEFAULT_STEPS


class ErrorBody(BaseModel):
    """Every error: `detail` (a string, or the list of validation errors for 422) and a one-line
    `message`."""

    detail: Any = Field(description="a string, or for 422 a list of {loc, msg, type}")
    message: str = Field(description="one readable line")


_WHY = {
    400: "malformed request (e.g. a body that is not UTF-8, a non-integer Content-Length)",
    401: "API key missing or wrong (when keys are configured)",
    403: "no API keys configured and the client is not on this machine",
    408: "the request head or body did not arrive in time",
    413: "request body larger than the server's limit",
    414: "URL longer than the server's limit",
    422: "invalid input: the message names the field and the rule",
    429: "rate limit of this API key / client exceeded, or too many wrong API keys from this address "
    "(Retry-After says when to retry)",
    431: "request headers larger than the server's limit",
    500: "internal error (the message carries the request id)",
    503: "model not ready, or the queue for this kind of work is full (Retry-After)",
    504: "not answered within the server's handler timeout",
}
COMMON_ERRORS = (400, 401, 403, 408, 413, 414, 422, 429, 431, 500, 503, 504)


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {code: {"model": ErrorBody, "description": _WHY[code]} for code in codes}


SWAGGER_UI = "/static/vendor/swagger-ui"


def install(app: FastAPI, settings: Any) -> None:
    """Generate the document once, with this server's ceilings written in; serve `/docs` (when
    `settings.docs`) from the vendored Swagger UI."""
    if settings.docs and app.openapi_url:
        openapi_url = app.openapi_url

        @app.get("/docs", include_in_schema=False)
        async def swagger_ui() -> HTMLResponse:
            return get_swagger_ui_html(
                openapi_url=openapi_url,
                title=f"{app.title} API",
                swagger_js_url=f"{SWAGGER_UI}/swagger-ui-bundle.js",
                swagger_css_url=f"{SWAGGER_UI}/swagger-ui.css",
                swagger_favicon_url="/static/favicon.svg",
                swagger_ui_parameters={"validatorUrl": None},
            )

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        doc = get_openapi(
            title=app.title, version=app.version, description=app.description, routes=app.routes
        )
        schemas = doc["components"]["schemas"]
        request = schemas["RolloutRequest"]
        props = request["properties"]
        for branch in props["steps"]["anyOf"] + props["recipe"]["anyOf"]:
            if branch.get("type") == "integer":
                branch["maximum"] = settings.max_steps
            elif branch.get("type") == "array":
                branch["maxItems"] = settings.max_steps
        props["meshes"]["maxItems"] = settings.max_meshes
        schemas["MeshSpec"]["properties"]["step"]["maximum"] = settings.max_steps
        if settings.max_steps < DEFAULT_STEPS:  # the default (100) would pass the ceiling: steps required
            request["anyOf"] = [  # ... unless a recipe sets it
                {"required": [name], "properties": {name: {"not": {"type": "null"}}}}
                for name in ("recipe", "steps")
            ]
        mesh = doc["paths"]["/rollouts/{rollout_id}/mesh"]["get"]
        for param in mesh["parameters"]:
            if param["name"] == "step":
                for branch in param["schema"].get("anyOf", [param["schema"]]):
                    if branch.get("type") == "integer":
                        branch["maximum"] = settings.max_steps
        app.openapi_schema = doc
        return doc

    app.openapi = openapi  # type: ignore[method-assign]
