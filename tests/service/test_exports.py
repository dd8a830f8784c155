"""Exports of a served rollout: metrics.csv, trajectory.h5 and the vtp mesh, checked against the rollout's
own JSON answer (the same numbers, the same states, the same surface), plus their gates."""

from __future__ import annotations

import base64
import csv
import io
import json
import xml.etree.ElementTree as ET

import h5py
import numpy as np
import pytest

from nemsim.controls import CONTROL_NAMES, CONTROL_SPECS
from nemsim.geometry.frame import FRAME


def _rollout(client, **body) -> dict:
    r = client.post("/rollout", json=body)
    assert r.status_code == 200, r.text
    return r.json()


def _csv(text: str) -> tuple[list[str], list[str], list[list[str]]]:
    """(comment lines, header, rows) of a metrics.csv."""
    lines = text.splitlines()
    comments = [line for line in lines if line.startswith("#")]
    table = list(csv.reader(line for line in lines if not line.startswith("#")))
    return comments, table[0], table[1:]


def test_metrics_csv_is_the_rollouts_metrics(client, default_controls):
    body = _rollout(client, controls=default_controls, steps=3)
    r = client.get(f"/rollouts/{body['id']}/metrics.csv")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("text/csv")
    assert f'filename="nemsim_{body["id"]}_metrics.csv"' in r.headers["content-disposition"]
    comments, header, rows = _csv(r.text)
    assert body["model_id"] in comments[0] and "scene tiny" in comments[0] and "voxel 8 nm" in comments[0]
    said = {line.split(":", 1)[0]: line.split(": ", 1)[1] for line in comments[1:]}  # "# name: value"
    assert json.loads(said["# geometry"]) == body["geometry"]
    assert json.loads(said["# controls (physical units)"]) == pytest.approx(body["controls"])
    assert said["# frame"].startswith(f"{FRAME}; depths (etch_depth, neck_depth) are below the initial")
    names = list(body["metrics"])
    assert header == ["step", "time [s]"] + [f"{n} [nm]" for n in names]
    assert [row[0] for row in rows] == ["0", "1", "2", "3"]
    assert [float(row[1]) for row in rows] == pytest.approx([0.0, 0.1, 0.2, 0.3])
    for j, name in enumerate(names):
        for k, row in enumerate(rows):
            value = body["metrics"][name][k]
            if value is None:  # undefined: an empty cell, never 0 or "nan"
                assert row[2 + j] == ""
            else:
                assert float(row[2 + j]) == pytest.approx(value, rel=1e-5, abs=1e-9)


def test_metrics_csv_of_a_recipe_has_control_columns(client, default_controls):
    second = {**default_controls, "flux_cl": 2 * default_controls["flux_cl"]}
    body = _rollout(client, recipe=[default_controls, second])
    comments, header, rows = _csv(client.get(f"/rollouts/{body['id']}/metrics.csv").text)
    assert any(line.startswith("# controls: a recipe of 2 control sets") for line in comments)
    control_cols = header[-len(CONTROL_NAMES) :]
    assert control_cols == [f"{s.name} [{s.unit}]" for s in CONTROL_SPECS]
    assert "flux_cl [mol m^-2 s^-1]" in control_cols and "angle_cl [1]" in control_cols
    assert rows[0][-len(CONTROL_NAMES) :] == [""] * len(CONTROL_NAMES)  # the initial state has no transition
    for k, controls in ((1, default_controls), (2, second)):
        got = dict(zip(CONTROL_NAMES, map(float, rows[k][-len(CONTROL_NAMES) :]), strict=True))
        assert got == pytest.approx(controls, rel=1e-12)


def test_trajectory_h5_holds_the_rollouts_states(
    client, default_controls, decode_fields, tiny_scene, tmp_path
):
    from nemsim.data.hdf5 import open_trajectories

    body = _rollout(client, controls=default_controls, steps=3, fields="all")
    r = client.get(f"/rollouts/{body['id']}/trajectory.h5")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/x-hdf5"
    assert f'filename="nemsim_{body["id"]}_trajectory.h5"' in r.headers["content-disposition"]
    fields = decode_fields(body["fields"])  # (4, 2, D, H, W) float16, what the JSON answer carried
    with h5py.File(io.BytesIO(r.content), "r") as f:
        assert f["states"].shape == (1, 4, *tiny_scene.state_shape) and f["states"].dtype == np.float16
        np.testing.assert_array_equal(f["states"][0], fields)
        assert f.attrs["model_id"] == body["model_id"] and f.attrs["rollout_id"] == body["id"]
        assert f.attrs["voxel_nm"] == tiny_scene.voxel_nm
        assert f.attrs["frame"] == FRAME  # the meshes' frame: the Si top at z = 0, the hole axis at x = y = 0
        v, half = tiny_scene.voxel_nm, tiny_scene.nx * tiny_scene.voxel_nm / 2
        assert [len(f.attrs[f"{a}_nm"]) for a in "zyx"] == list(tiny_scene.field_shape)
        assert f.attrs["x_nm"][1] == -half + v / 2 and f.attrs["x_nm"][-2] == half - v / 2
        assert f.attrs["z_nm"][tiny_scene.si_top] == -v / 2  # the top Si voxel's centre
        assert json.loads(f.attrs["scene"])["name"] == "tiny"
        assert json.loads(f.attrs["controls"]) == pytest.approx(body["controls"])
        depth = f["metrics/etch_depth"][()]
        assert f["metrics/etch_depth"].attrs["unit"] == "nm"
        assert depth == pytest.approx(np.array(body["metrics"]["etch_depth"], dtype=float), nan_ok=True)
    path = tmp_path / "rollout.h5"
    path.write_bytes(r.content)
    with open_trajectories(path) as traj:  # the reader of the simulator's data files
        assert traj.scene == tiny_scene and traj.n_cases == 1 and traj.n_states == 4
        assert traj.channel_names == ("mask", "si") and list(traj.case_ids) == [0]
        assert traj.times == pytest.approx([0.0, 0.1, 0.2, 0.3])
        np.testing.assert_array_equal(traj.states[0], fields.astype(np.float32))
        expected = [body["controls"][n] for n in CONTROL_NAMES]
        assert traj.controls_raw[0] == pytest.approx(expected)
        assert traj.controls_raw_schedule.shape == (1, 3, len(CONTROL_NAMES))


def _vtp_arrays(data: bytes) -> dict[str, np.ndarray]:
    """Every DataArray of a binary inline VTK XML file by name (UInt64 byte count, then the data)."""
    dtypes = {"Float32": "<f4", "Float64": "<f8", "Int64": "<i8", "UInt8": "u1"}
    out = {}
    for node in ET.fromstring(data).iter("DataArray"):
        raw = base64.b64decode(node.text or "")
        n = int(np.frombuffer(raw[:8], dtype="<u8")[0])
        assert n == len(raw) - 8
        values = np.frombuffer(raw[8:], dtype=dtypes[node.get("type", "")])
        out[node.get("Name", "")] = values.reshape(-1, int(node.get("NumberOfComponents", "1")))
    return out


def test_vtp_mesh_is_the_same_surface_as_ply(client, default_controls):
    import trimesh

    body = _rollout(client, controls=default_controls, steps=2)
    url = f"/rollouts/{body['id']}/mesh"
    r = client.get(url, params={"step": 2, "channel": "si", "format": "vtp"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("application/xml")
    assert "step2_si.vtp" in r.headers["content-disposition"]
    ply = client.get(url, params={"step": 2, "channel": "si", "format": "ply"}).content
    reference = trimesh.load(io.BytesIO(ply), file_type="ply", process=False)
    root = ET.fromstring(r.content)
    assert root.tag == "VTKFile" and root.get("type") == "PolyData" and root.get("header_type") == "UInt64"
    piece = root.find("PolyData/Piece")
    assert piece is not None and int(piece.get("NumberOfPoints", "")) == len(reference.vertices)
    arrays = _vtp_arrays(r.content)
    np.testing.assert_allclose(arrays["Points"], reference.vertices, atol=1e-4)  # nm, float32
    assert np.array_equal(arrays["connectivity"].reshape(-1, 3), reference.faces)
    assert np.array_equal(arrays["offsets"].ravel(), 3 * np.arange(1, len(reference.faces) + 1))
    assert np.allclose(np.linalg.norm(arrays["Normals"], axis=1), 1.0, atol=1e-5)
    assert arrays["step"].ravel().tolist() == [2.0]  # numeric provenance as FieldData
    head = r.content.split(b"<VTKFile")[0].decode()  # every provenance entry in the leading comment
    assert f'rollout_id: "{body["id"]}"' in head and f'model_id: "{body["model_id"]}"' in head
    assert f"frame: {json.dumps(FRAME)}" in head
    points = arrays["Points"]  # the frame: the box's faces at +-half a box (and half a voxel of padding)
    assert points[:, 0].min() == pytest.approx(-points[:, 0].max()) and points[:, 0].min() < -40


def test_inline_vtp_mesh(client, default_controls):
    body = _rollout(client, controls=default_controls, steps=1, meshes=[{"step": 1, "format": "vtp"}])
    mesh = body["meshes"][0]
    assert mesh["format"] == "vtp" and mesh["media_type"] == "application/xml"
    assert base64.b64decode(mesh["data"]) == client.get(mesh["url"]).content


@pytest.mark.parametrize("export", ["metrics.csv", "trajectory.h5", "mesh?format=vtp"])
def test_unknown_rollout_id_404(client, export):
    r = client.get(f"/rollouts/deadbeef/{export}")
    assert r.status_code == 404 and "unknown rollout id" in r.json()["message"]


def test_exports_are_behind_the_keys_and_the_rate_limit(make_client, served, default_controls):
    from service.served_model import RolloutResult

    result, _ = served.rollout(np.array([[default_controls[n] for n in CONTROL_NAMES]]))
    assert isinstance(result, RolloutResult)
    urls = [f"/rollouts/{result.id}/{e}" for e in ("metrics.csv", "trajectory.h5", "mesh?format=vtp")]
    keyed = make_client(api_keys="k" * 32)
    for url in urls:
        assert keyed.get(url).status_code == 401
        assert keyed.get(url, headers={"X-API-Key": "k" * 32}).status_code == 200
    limited = make_client(rate_limit_per_minute=1, rate_limit_burst=len(urls))
    assert [limited.get(url).status_code for url in urls] == [200] * len(urls)
    refused = limited.get(urls[0])
    assert refused.status_code == 429 and int(refused.headers["retry-after"]) > 0
