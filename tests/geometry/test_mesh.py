"""Surface meshes: nm coordinates (x, y, z) in the one frame (x, y from the hole axis, z above the initial
Si top), outward normals, export round-trips with provenance and the frame stated."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import trimesh

from nemsim.geometry.frame import FRAME, box_corner_nm, frame_to_index, grid_axes_nm
from nemsim.geometry.mesh import MESH_FORMATS, export_mesh, surface_mesh


def _sphere(scene, centre, radius):
    d, h, w = scene.field_shape
    z = np.arange(d)[:, None, None] - 1.0
    y = np.arange(h)[None, :, None] - 1.0
    x = np.arange(w)[None, None, :] - 1.0
    phi = np.sqrt((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2) - radius
    return np.clip(phi / scene.d_max_vox, -1, 1).astype(np.float32)


@pytest.fixture
def sphere_mesh(tiny_scene):
    # an off-centre sphere so a wrong axis order would show
    meta = {"case_id": 7, "step": 100, "controls": {"flux_cl": 1.5}}
    return surface_mesh(_sphere(tiny_scene, (5.0, 6.3, 14.0), 3.6), tiny_scene, meta)


def test_sphere_coordinates_and_orientation(tiny_scene, sphere_mesh):
    v = tiny_scene.voxel_nm
    centre_nm = (np.array([5.0, 6.3, 14.0]) + 0.5) * v + box_corner_nm(tiny_scene)
    r = np.linalg.norm(sphere_mesh.vertices - centre_nm, axis=1)
    assert np.all(np.abs(r - 3.6 * v) < 0.2 * v)
    assert sphere_mesh.is_watertight
    assert sphere_mesh.volume > 0  # outward normals
    out = np.einsum("ij,ij->i", sphere_mesh.face_normals, sphere_mesh.triangles_center - centre_nm)
    assert np.all(out > 0)
    assert sphere_mesh.metadata["units"] == "nm" and sphere_mesh.metadata["case_id"] == 7
    assert sphere_mesh.metadata["frame"] == FRAME


def test_frame_puts_the_si_top_at_z0_and_the_hole_axis_at_x_y_0(tiny_scene, make_hole):
    st = make_hole(tiny_scene, 2.0, 2.0)  # a hole of radius 2 voxels, 2 deep below the initial Si top
    m = surface_mesh(st[1], tiny_scene)
    v = tiny_scene.voxel_nm
    assert np.median(m.vertices[:, 2]) == pytest.approx(0.0, abs=1e-6)  # the flat Si top
    assert m.vertices[:, 2].min() == pytest.approx(-2.0 * v, abs=0.5 * v)  # the floor: depth = -z
    half = tiny_scene.nx * v / 2
    lateral = m.vertices[:, :2]
    assert lateral.min() == pytest.approx(-half - 0.5 * v) and lateral.max() == pytest.approx(half + 0.5 * v)
    floor = m.vertices[m.vertices[:, 2] < -1.5 * v]  # the hole floor lies round the axis
    assert np.abs(floor[:, :2].mean(axis=0)).max() < 0.1 * v
    axes = grid_axes_nm(tiny_scene)  # padded voxel centres: the same frame as the meshes
    assert axes["x"][1] == pytest.approx(-half + 0.5 * v) and axes["z"][tiny_scene.si_top + 1] == 0.5 * v
    grid = np.stack(np.meshgrid(axes["x"][:3], axes["y"][2:4], axes["z"][5:7], indexing="ij"), -1)
    idx = frame_to_index(grid.reshape(-1, 3), tiny_scene)  # (N, 3) padded (z, y, x)
    assert set(idx[:, 0]) == {5, 6} and set(idx[:, 1]) == {2, 3} and set(idx[:, 2]) == {0, 1, 2}


def _read_vtp(data: bytes) -> trimesh.Trimesh:
    """The triangles of a VTK XML PolyData file with inline binary arrays (UInt64 header), read by hand."""
    import base64
    import xml.etree.ElementTree as ET

    def array(node, name: str, dtype: str) -> np.ndarray:
        el = next(a for a in node.iter("DataArray") if a.get("Name") == name)
        raw = base64.b64decode(el.text.strip())
        n = int(np.frombuffer(raw[:8], dtype="<u8")[0])
        return np.frombuffer(raw[8 : 8 + n], dtype=dtype)

    piece = ET.fromstring(data).find("PolyData/Piece")
    faces = array(piece, "connectivity", "<i8").reshape(-1, 3)
    assert np.array_equal(array(piece, "offsets", "<i8"), 3 * np.arange(1, len(faces) + 1))
    assert int(piece.get("NumberOfPolys")) == len(faces)
    return trimesh.Trimesh(array(piece, "Points", "<f4").reshape(-1, 3), faces, process=False)


@pytest.mark.parametrize("fmt", MESH_FORMATS)
def test_export_round_trip(sphere_mesh, fmt):
    data = export_mesh(sphere_mesh, fmt)
    assert isinstance(data, bytes)
    if fmt == "vtp":  # trimesh reads no VTK files
        back = _read_vtp(data)
    else:
        back = trimesh.load(io.BytesIO(data), file_type=fmt, force="mesh")
    assert len(back.faces) == len(sphere_mesh.faces)
    assert back.volume == pytest.approx(sphere_mesh.volume, rel=1e-4)
    np.testing.assert_allclose(back.bounds, sphere_mesh.bounds, atol=1e-3)  # the frame kept, nm
    if fmt == "glb":
        assert back.metadata["frame"] == FRAME
        assert back.metadata["case_id"] == 7 and back.metadata["controls"] == {"flux_cl": 1.5}
    elif fmt == "ply":
        assert b"comment case_id=7" in data.split(b"end_header")[0]
        assert f"comment frame={json.dumps(FRAME)}".encode() in data.split(b"end_header")[0]
    elif fmt == "obj":
        assert data.decode().startswith("# NEMSim surface mesh") and "# case_id: 7" in data.decode()
        assert f"# frame: {json.dumps(FRAME)}" in data.decode()
    elif fmt == "vtp":
        assert b"NEMSim surface mesh" in data and b"case_id: 7" in data
        assert f"frame: {json.dumps(FRAME)}".encode() in data
    else:
        assert data[:80].startswith(b"NEMSim nm, x y from hole axis, z up from initial Si top; ")


def test_empty_field_and_bad_format(tiny_scene):
    m = surface_mesh(np.ones(tiny_scene.field_shape, np.float32), tiny_scene)
    assert len(m.vertices) == 0
    with pytest.raises(ValueError, match="glb"):
        export_mesh(m, "vtk")
    with pytest.raises(ValueError, match="field shape"):
        surface_mesh(np.ones((3, 3, 3)), tiny_scene)
