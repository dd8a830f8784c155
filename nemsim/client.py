"""A small Python client of the NEMSim service (`nemsim serve`): rollouts, mechanisms, meshes and
exports, inverse design and simulator jobs, one typed method each.

    from nemsim.client import Client

    nemsim = Client("http://127.0.0.1:8000")
    run = nemsim.rollout({"flux_cl": 0.01}, steps=50)  # the other controls: the documented defaults
    depth_nm = run["metrics"]["etch_depth"][-1]
    nemsim.trajectory(run["id"], "run.h5")

Choices:

* Standard library only (`urllib`): the library's dependencies hold no HTTP client (httpx comes with the
  service extra), and a client must work wherever `nemsim` is installed.
* Answers are the server's JSON as plain dicts; the `TypedDict`s below name the fields most used, so an
  editor completes them, without a second copy of the server's schema to keep in step.
* Every answer other than 2xx raises `ServiceError` with the status and the server's one-line `message`
  (its `detail` too: the list of validation errors of a 422); a server that cannot be reached raises
  `ServiceUnreachable`.
* A server that is busy says so with 429 or 503 and `Retry-After`: such an answer is retried after that
  delay (at most `max_wait_s` each time), `retries` times, before it is raised. Everything else is
  raised at once: a 4xx will not change by asking again.
* Jobs (`design`, `simulate`) are submitted and polled every `poll_s` until they end; one still running
  after its `timeout_s` is cancelled on the server (it would go on using a simulator) and `JobTimeout`
  raised. A job that failed or was cancelled raises `JobFailed` with the server's reason.
"""

from __future__ import annotations

import json
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, TypedDict

from nemsim import __version__

Channel = Literal["mask", "si"]
MeshFormat = Literal["glb", "ply", "obj", "stl", "vtp"]
Fields = Literal["none", "final", "all"]
JOB_ENDS = ("done", "failed", "cancelled")


class Rollout(TypedDict, total=False):
    """The answer of `Client.rollout` (`POST /rollout`; the server's schema has every field)."""

    id: str  # for meshes and exports of this rollout
    model_id: str
    steps: int
    cached: bool
    times_s: list[float]  # (steps + 1,) s
    metrics: dict[str, list[float | None]]  # name -> (steps + 1,) nm; None where undefined
    controls: dict[str, float]  # the full control set used (first transition), physical units
    defaulted: list[str]  # controls left out of the request and filled from the defaults
    recipe: list[dict[str, float]] | None
    warnings: list[str]
    fields: dict[str, Any] | None
    meshes: list[dict[str, Any]]
    intervals: dict[str, Any] | None


class Job(TypedDict, total=False):
    """A job's status (`GET /jobs/{id}`)."""

    id: str
    kind: str  # "design" or "simulation"
    status: Literal["pending", "running", "done", "failed", "cancelled"]
    progress: float  # 0..1
    created: float  # s since the epoch
    result: dict[str, Any] | None  # when done
    message: str | None  # why it failed


class ServiceError(RuntimeError):
    """The server answered with an error: `status` (HTTP), `message` (its one line), `detail` (the
    structured detail, e.g. the validation errors of a 422), `retry_after` (s, when it said)."""

    def __init__(self, status: int, message: str, detail: Any = None, retry_after: float | None = None):
        super().__init__(f"HTTP {status}: {message}")
        self.status = status
        self.message = message
        self.detail = detail
        self.retry_after = retry_after


class ServiceUnreachable(ConnectionError):
    """No answer from the server (refused, unknown host, timed out)."""


class JobFailed(RuntimeError):
    """A job ended as failed or cancelled; `job` is its last status."""

    def __init__(self, job: Job):
        super().__init__(
            f"job {job.get('id')} {job.get('status')}: {job.get('message') or 'no reason given'}"
        )
        self.job = job


class JobTimeout(TimeoutError):
    """A job did not end in time (it was cancelled on the server); `job` is its last status."""

    def __init__(self, job: Job, timeout_s: float):
        super().__init__(
            f"job {job.get('id')} still {job.get('status')} after {timeout_s:g} s "
            f"(progress {job.get('progress', 0.0):.0%}): cancel requested"
        )
        self.job = job


def _retry_after(headers: Any) -> float | None:
    value = headers.get("Retry-After")
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:  # the HTTP-date form: not sent by this server
        return None


def _error(status: int, body: bytes, headers: Any) -> ServiceError:
    """The server's error body ({"detail", "message"}) as a ServiceError; any other body as text."""
    try:
        parsed = json.loads(body)
    except ValueError:
        parsed = None
    if isinstance(parsed, dict):
        detail = parsed.get("detail")
        message = parsed.get("message") or (detail if isinstance(detail, str) else None)
    else:
        detail, message = None, None
    text = " ".join(body.decode("utf-8", "replace").split())[:300]
    return ServiceError(status, str(message or text or f"HTTP {status}"), detail, _retry_after(headers))


class Client:
    """The service at `base_url` (e.g. "http://127.0.0.1:8000"); `api_key`: sent as X-API-Key when the
    server requires keys; `timeout`: seconds per request; `retries`, `max_wait_s`: how often and how long
    a 429/503 with Retry-After is waited out (module docstring)."""

    def __init__(
        self,
        base_url: str,
        api_key: str | None = None,
        timeout: float = 120.0,
        *,
        retries: int = 3,
        max_wait_s: float = 30.0,
    ) -> None:
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout
        self.retries = retries
        self.max_wait_s = max_wait_s

    # --- transport ----------------------------------------------------------------------------------
    def _request(
        self, method: str, path: str, *, body: Any = None, query: Iterable[tuple[str, Any]] = ()
    ) -> tuple[bytes, str]:
        """(body, content type) of a 2xx answer; ServiceError / ServiceUnreachable otherwise."""
        url = self.base_url + path
        pairs = [(k, v) for k, v in query if v is not None]
        if pairs:
            url += "?" + urllib.parse.urlencode(pairs)
        headers = {"Accept": "application/json, */*", "User-Agent": f"nemsim-client/{__version__}"}
        data = None
        if body is not None:
            data = json.dumps(body, allow_nan=False).encode()
            headers["Content-Type"] = "application/json"
        if self.api_key:
            headers["X-API-Key"] = self.api_key
        attempt = 0
        while True:
            req = urllib.request.Request(url, data=data, headers=headers, method=method)
            try:
                with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                    return resp.read(), resp.headers.get("Content-Type", "")
            except urllib.error.HTTPError as exc:
                error = _error(exc.code, exc.read(), exc.headers)
                exc.close()
                if exc.code not in (429, 503) or error.retry_after is None or attempt >= self.retries:
                    raise error from None
            except (urllib.error.URLError, TimeoutError, ConnectionError) as exc:
                reason = getattr(exc, "reason", exc)
                raise ServiceUnreachable(f"{method} {url}: no answer ({reason})") from None
            attempt += 1
            time.sleep(min(error.retry_after, self.max_wait_s))

    def _json(self, method: str, path: str, **kwargs: Any) -> Any:
        return json.loads(self._request(method, path, **kwargs)[0])

    @staticmethod
    def _segment(value: str) -> str:
        return urllib.parse.quote(str(value), safe="")

    # --- service ------------------------------------------------------------------------------------
    def ready(self) -> bool:
        """The model is loaded and warmed up (`GET /ready` answered 200); False while it loads, after a
        failed load, or when nothing answers."""
        try:
            self._request("GET", "/ready")
        except (ServiceError, ServiceUnreachable):
            return False
        return True

    def wait_ready(self, timeout_s: float = 300.0, poll_s: float = 0.5) -> None:
        """Block until `ready()`; TimeoutError after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while not self.ready():
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.base_url} not ready after {timeout_s:g} s")
            time.sleep(poll_s)

    def model(self) -> dict[str, Any]:
        """The served model (`GET /model`): id, scene, controls with units, ranges and defaults, errors."""
        return self._json("GET", "/model")

    # --- rollouts -----------------------------------------------------------------------------------
    def rollout(
        self,
        controls: Mapping[str, float] | None = None,
        *,
        steps: int | None = None,
        recipe: Sequence[Mapping[str, float]] | None = None,
        controls_normalized: Sequence[float] | None = None,
        fields: Fields = "none",
        meshes: Sequence[Mapping[str, Any]] = (),
        intervals: bool = False,
        geometry: Mapping[str, Any] | None = None,
    ) -> Rollout:
        """Predict the etch (`POST /rollout`). Give `controls` (any subset by name, physical units; the rest
        take the defaults and are named in the answer's `defaulted`), a `recipe` (one set per transition)
        or `controls_normalized` (14 numbers); with none of them, every control is at its default.
        `steps`: transitions of 0.1 s (server default 100, or the recipe's length). `geometry`: the feature,
        {"kind": "hole" | "trench", "cd_nm", "mask_nm"} (None: the model's own)."""
        body: dict[str, Any] = {"fields": fields, "meshes": [dict(m) for m in meshes], "intervals": intervals}
        if geometry is not None:
            body["geometry"] = dict(geometry)
        if recipe is not None:
            body["recipe"] = [dict(row) for row in recipe]
        elif controls_normalized is not None:
            body["controls_normalized"] = [float(v) for v in controls_normalized]
        else:
            body["controls"] = dict(controls or {})
        if steps is not None:
            body["steps"] = steps
        return self._json("POST", "/rollout", body=body)

    def mesh(
        self, rollout_id: str, step: int | None = None, channel: Channel = "si", format: MeshFormat = "glb"
    ) -> bytes:
        """The surface file of one channel at one step (default: the final state) of a rollout, in nm
        (x, y from the hole axis, z above the initial Si top: ``nemsim.geometry.frame``)."""
        query = [("step", step), ("channel", channel), ("format", format)]
        return self._request("GET", f"/rollouts/{self._segment(rollout_id)}/mesh", query=query)[0]

    def metrics_csv(self, rollout_id: str) -> str:
        """The rollout's profile metrics as CSV text (one row per state, nm, empty cells where undefined)."""
        return self._request("GET", f"/rollouts/{self._segment(rollout_id)}/metrics.csv")[0].decode("utf-8")

    def trajectory(self, rollout_id: str, path: str | Path) -> Path:
        """Save every state of the rollout as HDF5 (the simulator's data-file layout) to `path`."""
        data = self._request("GET", f"/rollouts/{self._segment(rollout_id)}/trajectory.h5")[0]
        out = Path(path)
        out.write_bytes(data)
        return out

    def mechanisms(
        self,
        controls: Mapping[str, float] | None = None,
        *,
        factors: Sequence[float] | None = None,
        geometry: Mapping[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Cl+ / neutral-Cl interventions around one control set (`GET /mechanisms`, with `geometry`
        `POST /mechanisms`; missing controls take the defaults); `factors`: flux multiplier levels (server
        default 0.5 and 1.5); `geometry`: the feature (None: the model's own)."""
        if geometry is not None:
            body: dict[str, Any] = {"controls": dict(controls or {}), "geometry": dict(geometry)}
            if factors:
                body["factors"] = [float(f) for f in factors]
            return self._json("POST", "/mechanisms", body=body)
        query: list[tuple[str, Any]] = [(k, repr(float(v))) for k, v in (controls or {}).items()]
        query += [("factors", repr(float(f))) for f in factors or ()]
        return self._json("GET", "/mechanisms", query=query)

    # --- jobs ---------------------------------------------------------------------------------------
    def job(self, job_id: str) -> Job:
        """A job's status, progress and (when done) result."""
        return self._json("GET", f"/jobs/{self._segment(job_id)}")

    def cancel(self, job_id: str) -> Job:
        """Cancel a pending or running job; its status becomes `cancelled` once it stopped."""
        return self._json("DELETE", f"/jobs/{self._segment(job_id)}")

    def wait(self, job_id: str, timeout_s: float = 600.0, poll_s: float = 0.5) -> dict[str, Any]:
        """Poll a job until it ends: its result when done; JobFailed when it failed or was cancelled;
        JobTimeout (after cancelling it) when it is still running after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while True:
            status = self.job(job_id)
            if status.get("status") == "done":
                return status.get("result") or {}
            if status.get("status") in JOB_ENDS:
                raise JobFailed(status)
            if time.monotonic() > deadline:
                try:
                    status = self.cancel(job_id)
                except ServiceError:  # ended or forgotten meanwhile: nothing to cancel
                    pass
                raise JobTimeout(status, timeout_s)
            time.sleep(poll_s)

    def design(
        self,
        targets: Mapping[str, float | Mapping[str, float]],
        *,
        step: int | None = None,
        fixed: Mapping[str, float] | None = None,
        bounds: Mapping[str, tuple[float, float]] | None = None,
        k: int = 3,
        verify: bool = False,
        timeout_s: float = 600.0,
        poll_s: float = 0.5,
        **options: Any,
    ) -> dict[str, Any]:
        """Inverse design (`POST /design`, then the job polled until it ends; `wait`): recipes whose
        predicted profile meets `targets` (nm per metric, a number or {"value", "tol"}) at `step`.
        `options`: the request's other fields (secondary, seed, verify_top, refine, ...)."""
        wanted = {n: t if isinstance(t, int | float) else dict(t) for n, t in targets.items()}
        body: dict[str, Any] = {"targets": wanted, "k": k, "verify": verify, **options}
        if step is not None:
            body["step"] = step
        if fixed:
            body["fixed"] = dict(fixed)
        if bounds:
            body["bounds"] = {n: list(b) for n, b in bounds.items()}
        created = self._json("POST", "/design", body=body)
        return self.wait(created["id"], timeout_s, poll_s)

    def simulate(
        self,
        controls: Mapping[str, float] | None = None,
        *,
        steps: int | None = None,
        recipe: Sequence[Mapping[str, float]] | None = None,
        seed: int = 1,
        timeout_s: float = 600.0,
        poll_s: float = 0.5,
        geometry: Mapping[str, Any] | None = None,
    ) -> dict[str, Any]:
        """Run the simulator on these controls and compare the surrogate with it (`POST /simulations`,
        then `wait`): the comparison, with the simulator's and the model's metrics. `geometry`: the
        feature (None: the model's own; `design` takes it among its options too)."""
        body: dict[str, Any] = {"seed": seed}
        if geometry is not None:
            body["geometry"] = dict(geometry)
        if recipe is not None:
            body["recipe"] = [dict(row) for row in recipe]
        else:
            body["controls"] = dict(controls or {})
        if steps is not None:
            body["steps"] = steps
        created = self._json("POST", "/simulations", body=body)
        return self.wait(created["id"], timeout_s, poll_s)
