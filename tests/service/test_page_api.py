"""What the explorer page needs besides the rollout API: the page and its files (no remote resources, a
CSP that allows only this origin), the controls' meaning and defaults on /model, and the cross-sections."""

from __future__ import annotations

import base64
import re

import numpy as np


def test_page_and_static_files_are_served_with_a_same_origin_csp(make_client):
    client = make_client()
    r = client.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assert "default-src 'self'" in r.headers["content-security-policy"]
    refs = re.findall(r'(?:src|href)="([^"]+)"', r.text)
    assert refs and all(ref.startswith("/") for ref in refs), refs  # nothing from another origin
    for ref in refs:
        assert client.get(ref).status_code == 200, ref
    assert client.get("/static/vendor/three/LICENSE").status_code == 200
    assert client.get("/model").headers["content-security-policy"].startswith("default-src 'none'")


def test_model_lists_each_controls_meaning_and_default(make_client):
    controls = make_client().get("/model").json()["controls"]
    assert len(controls) == 14
    for c in controls:
        assert c["description"] and c["train_min"] <= c["default"] <= c["train_max"]


def test_slices_cover_every_state_through_the_hole_axis(make_client, default_controls):
    client = make_client()
    run = client.post("/rollout", json={"controls": default_controls, "steps": 4}).json()
    body = client.get(f"/rollouts/{run['id']}/slices").json()
    n, c, d, w = body["shape"]
    assert (n, c) == (5, 2)
    q = np.frombuffer(base64.b64decode(body["data"]), dtype=np.uint8).reshape(body["shape"])
    sdf = q / 127.5 - 1.0
    centre = w // 2
    assert sdf[0, 1, 1, centre] < 0 < sdf[0, 1, -2, centre]  # Si at the bottom, vacuum at the top
    r = client.get("/rollouts/nope/slices")
    assert r.status_code == 404 and "unknown rollout id" in r.json()["message"]


def test_the_page_modules_import_only_files_the_server_serves(make_client):
    """The page is ES modules: every import (followed through the page's own modules) is a same-origin file
    served as JavaScript, so a renamed or missing module cannot leave the page blank."""
    client = make_client()
    seen, todo = set(), ["/static/explorer.js"]
    while todo:
        path = todo.pop()
        r = client.get(path)
        assert r.status_code == 200 and "javascript" in r.headers["content-type"], path
        seen.add(path)
        if path.startswith("/static/vendor/"):
            continue
        for ref in re.findall(r"""^import [^;]*?from '([^']+)';""", r.text, re.M):
            assert ref.startswith("/static/"), f"{path} imports {ref}"
            if ref not in seen:
                todo.append(ref)
    own = {f"/static/{name}.js" for name in ("explorer", "api", "plot", "view3d", "design")}
    assert own <= seen and "/static/vendor/three/three.module.min.js" in seen
