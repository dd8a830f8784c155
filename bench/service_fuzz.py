"""Seeded fuzz of the request bodies of `POST /rollout`, `/design` and `/simulations` on a live server.

Every case is built from a valid body by one mutation, and knows what the server must do with it:

* `guard`: a value past a documented guard (a control above its accepted maximum or below its physical
  minimum, in `controls`, `controls_normalized`, a recipe row, `fixed` or `bounds`; a target of +-1e308,
  a negative or a non-finite one, or one beyond the scene; a tolerance of 1e-300, 0 or beyond the
  metric's range; steps past the server's ceiling or the horizon; a 5,000-digit integer; a seed out of
  range): must be refused (4xx). A 2xx is an *out-of-guard request accepted*.
* `malformed`: wrong types, missing or extra keys, fractional exponents, two control sources, broken or
  non-UTF-8 JSON, 100,000-deep nesting, a body over the size limit: must be refused too.
* `valid`: a body inside every guard (few: each runs a rollout or starts a job, which is cancelled at
  once), a control left out among them (it takes its default): should be accepted (2xx, or 429 at the
  client's job cap).

Reported: status counts per route and class, answers >= 500, accepted `guard` and `malformed` cases (with
examples), refused `valid` ones, and error bodies that are not JSON or show a traceback or a file path.
Requests come from many loopback addresses (so the per-client rate limit, a limit on one client, does not
turn the fuzz into a test of itself), except the valid job submissions, all from one address, so they
meet the per-client job cap and never fill the job queue.
"""

from __future__ import annotations

import json
import random
import threading
import time
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np

from bench.live_server import LiveServer, centre_controls, count, random_controls, server_errors
from nemsim.controls import ACCEPT_MAX, CONTROL_NAMES, CONTROL_SPECS, PHYS_MIN

ROUTES = ("/rollout", "/design", "/simulations")
LEAK_MARKS = ("Traceback", 'File "', "site-packages", '.py"', "/home/", "/tmp/", "/work/", "/usr/")
JOB_SOURCE = "127.0.3.1"  # the one address of the valid job submissions


@dataclass
class Case:
    route: str
    kind: str  # the mutation
    cls: str  # guard | malformed | valid
    body: bytes
    content_type: str = "application/json"


HUGE = "<5000-digit integer>"  # stands for a JSON integer of 5,000 digits (Python refuses to print one)


def _dump(obj: Any) -> bytes:
    """JSON text: NaN / Infinity tokens where a float is non-finite, `HUGE` as 5,000 nines."""
    return json.dumps(obj, allow_nan=True).replace(json.dumps(HUGE), "9" * 5000).encode()


class CaseMaker:
    """Seeded cases (module docstring). `max_steps`, `horizon`: the server's ceiling and the model's;
    `scene`: a `nemsim.scenes.Scene` for target ranges (None: no valid /design bodies)."""

    def __init__(self, seed: int, max_steps: int, horizon: int, scene: Any) -> None:
        self.r = random.Random(seed)
        self.np = np.random.default_rng(seed)
        self.max_steps, self.horizon, self.scene = max_steps, horizon, scene
        self.design_options: dict[str, list[Any]] = {  # out-of-range values of /design's options
            "step": [0, -1, 10_001, horizon + 1, 2**63, HUGE],
            "k": [0, -1, 11, 2**63],
            "verify_top": [0, -1, 4],
            "refine_rounds": [-1, 6],
            "seed": [-1, 2**31, 2**63],
            "sim_seed": [-1, 2**63, 10**30],
        }

    # --- values -------------------------------------------------------------------------------------
    def _above(self, j: int) -> Any:
        hi = float(ACCEPT_MAX[j])
        return self.r.choice([hi * (1 + 1e-6) + 1e-9, hi * 10, 1e30, 1e308, HUGE])

    def _below(self, j: int) -> float:
        lo = float(PHYS_MIN[j])
        return self.r.choice([lo - max(1e-9, abs(lo) * 1e-6), lo - 1.0, -1e308])

    def _out_of_guard(self, j: int) -> Any:
        return self._above(j) if self.r.random() < 0.6 else self._below(j)

    def _wrong_type(self) -> Any:
        return self.r.choice(["1.0", True, None, [], {}, "NaN"])

    def _controls(self) -> dict[str, Any]:
        return random_controls(self.np)

    def _steps(self) -> int:
        return self.r.randint(1, min(4, self.max_steps))

    # --- control sources (rollout and simulations) --------------------------------------------------
    def _source_case(self, route: str) -> tuple[str, str, dict[str, Any] | bytes]:
        """(kind, class, body) of a rollout / simulation request."""
        body: dict[str, Any] = {"controls": self._controls(), "steps": self._steps()}
        j = self.r.randrange(len(CONTROL_NAMES))
        name = CONTROL_NAMES[j]
        pick = self.r.random()
        if pick < 0.04:
            return "valid", "valid", body
        if pick < 0.30:
            body["controls"][name] = self._out_of_guard(j)
            return "control_out_of_guard", "guard", body
        if pick < 0.36:
            body["controls"][name] = self.r.choice([float("nan"), float("inf"), float("-inf")])
            return "control_non_finite", "guard", body
        if pick < 0.46:
            steps = self.r.choice([self.max_steps + 1, 10_001, 10**9, HUGE, 0, -1])
            if route == "/simulations" and self.r.random() < 0.5:
                steps = self.horizon + 1
            body["steps"] = steps
            return "steps_out_of_guard", "guard", body
        if pick < 0.54:
            vec = [self.r.uniform(-1, 1) for _ in CONTROL_NAMES]
            from service.schemas import NORM_MAX, NORM_MIN

            vec[j] = float(NORM_MAX[j]) * 1.001 + 1e-6 if self.r.random() < 0.6 else float(NORM_MIN[j]) - 1e-3
            return "normalized_out_of_guard", "guard", {"controls_normalized": vec, "steps": body["steps"]}
        if pick < 0.62:
            rows = [self._controls() for _ in range(self.r.randint(1, 4))]
            rows[self.r.randrange(len(rows))][name] = self._out_of_guard(j)
            return "recipe_out_of_guard", "guard", {"recipe": rows}
        if pick < 0.66 and route == "/simulations":
            body["seed"] = self.r.choice([-1, 2**63, 10**30])
            return "seed_out_of_range", "guard", body
        return self._malformed_source(route, body, name)

    def _malformed_source(self, route: str, body: dict[str, Any], name: str) -> tuple[str, str, Any]:
        kind = self.r.choice(
            [
                "wrong_type",
                "missing",
                "extra",
                "fraction",
                "two_sources",
                "no_source",
                "steps_type",
                "normalized_length",
                "recipe_mismatch",
                "option",
            ]
        )
        if kind == "wrong_type":
            body["controls"][name] = self._wrong_type()
        elif kind == "missing":  # a control left out takes its default: a valid body
            del body["controls"][name]
            return kind, "valid", body
        elif kind == "extra":
            body[self.r.choice(["control", "Steps", "__proto__", "x" * 300])] = 1
        elif kind == "fraction":
            ints = [s.name for s in CONTROL_SPECS if s.kind == "int"]
            body["controls"][self.r.choice(ints)] = self.r.choice([2.5, 10.25, 1.0000001])
        elif kind == "two_sources":
            body["controls_normalized"] = [0.0] * len(CONTROL_NAMES)
        elif kind == "no_source":
            del body["controls"]
        elif kind == "steps_type":
            body["steps"] = self.r.choice(["5", True, 2.5, [], {}])
        elif kind == "normalized_length":
            n = self.r.choice([0, 1, len(CONTROL_NAMES) - 1, len(CONTROL_NAMES) + 1])
            return kind, "malformed", {"controls_normalized": [0.0] * n, "steps": body["steps"]}
        elif kind == "recipe_mismatch":
            return kind, "malformed", {"recipe": [self._controls()] * 2, "steps": 3}
        elif route == "/rollout":
            body[self.r.choice(["fields", "intervals", "meshes"])] = self.r.choice(
                [
                    "yes",
                    "all_of_them",
                    1,
                    [{"step": 10_001}],
                    [{"step": 0, "format": "exe"}],
                    [{"step": 0}] * 9,
                ]
            )
        else:
            body["seed"] = self.r.choice(["1", 1.5, True])
        return kind, "malformed", body

    # --- design ---------------------------------------------------------------------------------
    def _design_case(self) -> tuple[str, str, dict[str, Any] | bytes]:
        metric = self.r.choice(["etch_depth", "top_width", "bottom_width", "mask_loss", "bowing"])
        body: dict[str, Any] = {"targets": {metric: {"value": 10.0, "tol": 3.0}}, "k": 1}
        if self.scene is not None:
            from nemsim.analysis.inverse.spec import target_range

            lo, hi, _ = target_range(metric, self.scene)
            body["targets"][metric] = {"value": self.r.uniform(lo, hi), "tol": min(3.0, (hi - lo) / 2)}
        j = self.r.randrange(len(CONTROL_NAMES))
        name = CONTROL_NAMES[j]
        pick = self.r.random()
        if pick < 0.03 and self.scene is not None:
            return "valid", "valid", body
        if pick < 0.25:
            body["targets"][metric]["value"] = self.r.choice(
                [1e308, -1e308, -1.0, -1e-300, 1e6, float("nan"), float("inf"), HUGE]
            )
            if self.r.random() < 0.3:
                body["targets"][metric] = body["targets"][metric]["value"]  # the bare-number form
            return "target_out_of_guard", "guard", body
        if pick < 0.45:
            body["targets"][metric]["tol"] = self.r.choice(
                [1e-300, 0.0, -1.0, 0.05, 1e6, 1e308, float("nan")]
            )
            return "tol_out_of_guard", "guard", body
        if pick < 0.62:
            body["fixed"] = {name: self.r.choice([self._out_of_guard(j), float("nan"), float("inf")])}
            return "fixed_out_of_guard", "guard", body
        if pick < 0.74:
            good = float(CONTROL_SPECS[j].low)
            body["bounds"] = {name: self.r.choice([[good, self._above(j)], [self._below(j), good]])}
            return "bounds_out_of_guard", "guard", body
        if pick < 0.82:
            option = self.r.choice(list(self.design_options))
            body[option] = self.r.choice(self.design_options[option])
            return "option_out_of_range", "guard", body
        kind = self.r.choice(["metric", "empty", "fixed_name", "bounds_shape", "bounds_order", "types"])
        if kind == "metric":
            body["targets"] = {"depth_of_everything": 10.0}
        elif kind == "empty":
            body["targets"] = {}
        elif kind == "fixed_name":
            body["fixed"] = {self.r.choice(["flux", "", "x" * 200]): 1.0}
        elif kind == "bounds_shape":
            body["bounds"] = {name: self.r.choice([[1.0], [1.0, 2.0, 3.0], "1..2", 5])}
        elif kind == "bounds_order":
            v = float(CONTROL_SPECS[j].high)
            body["bounds"] = {name: [v, v * 0.5]}
        else:
            # (null is no malformed value here: `step` may be null, the default)
            body[self.r.choice(["k", "step", "fixed", "targets"])] = self.r.choice(["3", True, [], "x"])
        return kind, "malformed", body

    # --- any route -----------------------------------------------------------------------------
    def _raw(self) -> tuple[str, str, bytes, str]:
        kind = self.r.choice(
            [
                "truncated",
                "not_utf8",
                "garbage",
                "deep_nesting",
                "oversize",
                "not_object",
                "wrong_content_type",
            ]
        )
        ct = "application/json"
        if kind == "truncated":
            text = _dump({"controls": self._controls(), "steps": 3})
            raw = text[: self.r.randrange(1, len(text) - 1)]
        elif kind == "not_utf8":
            raw = b'{"steps": "\xff\xfe"}'
        elif kind == "garbage":
            raw = bytes(self.r.getrandbits(8) for _ in range(self.r.randint(1, 64)))
        elif kind == "deep_nesting":
            depth = self.r.choice([1_000, 100_000])
            raw = b"[" * depth + b"]" * depth
        elif kind == "oversize":
            raw = _dump({"controls": self._controls(), "pad": "x" * 1_100_000})
        elif kind == "not_object":
            raw = _dump(self.r.choice([[], 3, "controls", None]))
        else:
            raw, ct = b"controls=1&steps=3", "application/x-www-form-urlencoded"
        return kind, "malformed", raw, ct

    def next(self) -> Case:
        route = self.r.choices(ROUTES, weights=(5, 3, 2))[0]
        if self.r.random() < 0.06:
            kind, cls, raw, ct = self._raw()
            return Case(route, kind, cls, raw, ct)
        kind, cls, body = self._design_case() if route == "/design" else self._source_case(route)
        return Case(route, kind, cls, body if isinstance(body, bytes) else _dump(body))


def fuzz(
    server: LiveServer,
    *,
    calls: int,
    seed: int,
    workers: int = 4,
    scene: Any = None,
    max_steps: int = 100,
    horizon: int = 100,
    time_cap_s: float = 600.0,
) -> dict[str, Any]:
    """Send `calls` fuzz cases (module docstring) from `workers` threads; the report."""
    lock = threading.Lock()
    codes: dict[str, dict[str, int]] = {}
    by_kind: dict[str, dict[str, int]] = {}
    answers: dict[str, dict[str, str]] = {}  # the first answer per mutation and status
    accepted: dict[str, list[str]] = {"guard": [], "malformed": []}
    refused_valid: list[str] = []
    leaks: list[str] = []
    non_json: list[str] = []
    transport: list[str] = []
    jobs = {"created": 0, "cancelled": 0}
    sent = [0]
    deadline = time.monotonic() + time_cap_s

    def record(case: Case, status: int | str, text: str) -> None:
        label = f"{case.route} {case.kind}"
        with lock:
            count(codes.setdefault(f"{case.route} {case.cls}", {}), status)
            count(by_kind.setdefault(label, {}), status)
            answers.setdefault(label, {}).setdefault(str(status), text[:160])
            if isinstance(status, str):
                transport.append(f"{label}: {status}")
                return
            if 200 <= status < 300 and case.cls != "valid":
                accepted[case.cls].append(f"{label}: {case.body[:200]!r}")
            if case.cls == "valid" and status >= 400 and status != 429:
                refused_valid.append(f"{label} -> {status}: {text[:200]}")
            if status >= 400:
                if any(m in text for m in LEAK_MARKS):
                    leaks.append(f"{label} -> {status}: {text[:200]}")
                try:
                    json.loads(text)
                except ValueError:
                    non_json.append(f"{label} -> {status}: {text[:100]!r}")

    def worker(w: int) -> None:
        maker = CaseMaker(seed * 1_000 + w, max_steps, horizon, scene)
        sources = [f"127.0.2.{w * 16 + i + 1}" for i in range(16)]
        clients = [_client(server, s) for s in sources]
        job_client = _client(server, JOB_SOURCE)
        try:
            for i in range(calls // workers + (w < calls % workers)):
                if time.monotonic() > deadline:
                    return
                case = maker.next()
                is_job = case.cls == "valid" and case.route != "/rollout"
                http = job_client if is_job else clients[i % len(clients)]
                status: int | str
                try:
                    r = http.post(case.route, content=case.body, headers={"content-type": case.content_type})
                    status, text = r.status_code, r.text
                except httpx.HTTPError as exc:
                    status, text = type(exc).__name__, ""
                record(case, status, text)
                with lock:
                    sent[0] += 1
                if isinstance(status, int) and status == 202:
                    job_id = r.json().get("id", "")
                    d = http.delete(f"/jobs/{job_id}")
                    with lock:
                        jobs["created"] += 1
                        jobs["cancelled"] += d.status_code == 200
        finally:
            for c in [*clients, job_client]:
                c.close()

    t0 = time.monotonic()
    threads = [threading.Thread(target=worker, args=(w,)) for w in range(workers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - t0
    totals: dict[str, int] = {}
    for route_codes in codes.values():
        for c, n in route_codes.items():
            totals[c] = totals.get(c, 0) + n
    return {
        "calls": sent[0],
        "calls_asked": calls,
        "seed": seed,
        "wall_s": wall,
        "workers": workers,
        "status": totals,
        "status_by_route_and_class": codes,
        "status_by_mutation": by_kind,
        "first_answer_by_mutation": answers,
        "server_errors_5xx": server_errors(totals),
        "transport_failures": len(transport),
        "out_of_guard_accepted": len(accepted["guard"]),
        "malformed_accepted": len(accepted["malformed"]),
        "accepted_examples": (accepted["guard"] + accepted["malformed"])[:10],
        "guard_cases": sum(n for k, v in codes.items() if k.endswith(" guard") for n in v.values()),
        "valid_refused": len(refused_valid),
        "valid_refused_examples": refused_valid[:5],
        "error_bodies_leaking": len(leaks),
        "leak_examples": leaks[:5],
        "error_bodies_not_json": len(non_json),
        "not_json_examples": non_json[:5],
        "rate_limited_429": totals.get("429", 0),
        "jobs_created_and_cancelled": jobs,
    }


def _client(server: LiveServer, source: str) -> httpx.Client:
    from bench.live_server import client

    return client(server, source=source, timeout_s=60.0)


__all__ = ["Case", "CaseMaker", "centre_controls", "fuzz"]
