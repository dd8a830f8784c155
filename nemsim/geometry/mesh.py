"""Surface meshes of one SDF channel, in nm, and their export to glb / ply / obj / stl.

Coordinates. The field is a padded, transposed (D, H, W) = (z, y, x) channel (index = native + 1).
Marching cubes (scikit-image, level 0, unit spacing) gives vertices in index coordinates; we undo the
padding (-1) and the transposition ((z, y, x) -> (x, y, z)) and convert voxel-centre coordinates to nm
with the voxel spanning [i, i + 1) * voxel_nm, i.e. position_nm = (native + 0.5) * voxel_nm. So the
initial Si top surface of a scene sits at z = si_top * voxel_nm and the box spans
[0, nx * voxel_nm] x [0, ny * voxel_nm] x [0, nz * voxel_nm]; the padding voxels extend the surface by
half a voxel beyond the box so that it reaches the box faces. Faces are wound so that normals point out
of the material (towards increasing SDF, i.e. into vacuum).

Provenance: ``metadata`` (a JSON-serializable dict) is stored in ``mesh.metadata`` and embedded where the
format allows it: glb mesh ``extras``, ply ``comment`` header lines (one ``key=json`` per line), an obj
``#`` comment header, and (truncated to 80 bytes) the binary stl header.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

if TYPE_CHECKING:
    import trimesh

    from nemsim.scenes import Scene

MeshFormat = Literal["glb", "ply", "obj", "stl"]
MESH_FORMATS: tuple[str, ...] = ("glb", "ply", "obj", "stl")
MEDIA_TYPES = {
    "glb": "model/gltf-binary",
    "ply": "application/octet-stream",
    "obj": "model/obj",
    "stl": "model/stl",
}


def surface_mesh(field: Any, scene: Scene, metadata: dict | None = None) -> trimesh.Trimesh:
    """Zero level set of one normalized SDF channel as a triangle mesh in nm, (x, y, z) order.

    Args:
        field: (D, H, W) normalized SDF channel of ``scene`` (numpy or CPU torch); negative inside.
        scene: gives the voxel size and the padded shape.
        metadata: provenance stored in ``mesh.metadata`` (and embedded by :func:`export_mesh`).
    Returns:
        ``trimesh.Trimesh``; empty (no vertices) when the channel has no zero crossing.
    """
    import trimesh
    from skimage.measure import marching_cubes

    if hasattr(field, "detach"):
        field = field.detach().cpu().numpy()
    f = np.ascontiguousarray(field, dtype=np.float32)
    if f.shape != scene.field_shape:
        raise ValueError(f"field shape {f.shape} != scene {scene.name!r} field shape {scene.field_shape}")
    meta = dict(metadata or {})
    meta.setdefault("units", "nm")
    meta.setdefault("scene", scene.name)
    if not (float(f.min()) < 0.0 < float(f.max())):
        empty = np.zeros((0, 3))
        return trimesh.Trimesh(vertices=empty, faces=empty.astype(np.int64), metadata=meta)
    # 'ascent' winding in (z, y, x) index space becomes outward (towards increasing SDF) once the axis
    # order is reversed below (a mirror); checked on a sphere in tests/geometry/test_mesh.py
    verts, faces, _, _ = marching_cubes(
        f, level=0.0, spacing=(1.0, 1.0, 1.0), gradient_direction="ascent", allow_degenerate=False
    )
    xyz = (verts[:, ::-1] - 1.0 + 0.5) * scene.voxel_nm  # (V, 3): unpad, (z,y,x)->(x,y,z), centres -> nm
    # process=True merges the duplicate vertices marching cubes emits where the SDF is exactly 0 at a voxel
    return trimesh.Trimesh(vertices=xyz, faces=faces, process=True, metadata=meta)


def _provenance(mesh: trimesh.Trimesh) -> dict:
    meta = mesh.metadata or {}
    return {str(k): v for k, v in meta.items() if not str(k).startswith("_")}


def _ply_with_comments(data: bytes, meta: dict) -> bytes:
    head_end = data.index(b"end_header\n")
    header = data[:head_end].decode("ascii").splitlines()
    # PLY comments are single header lines after "format"
    comments = [f"comment {k}={json.dumps(v, separators=(',', ':'), default=str)}" for k, v in meta.items()]
    comments = [c.replace("\n", " ").replace("\r", " ") for c in comments]
    fmt_idx = next(i for i, line in enumerate(header) if line.startswith("format"))
    header = header[: fmt_idx + 1] + comments + header[fmt_idx + 1 :]
    return ("\n".join(header) + "\n").encode("ascii", errors="replace") + data[head_end:]


def export_mesh(mesh: trimesh.Trimesh, fmt: str) -> bytes:
    """Serialize a mesh to one of ``MESH_FORMATS``, embedding ``mesh.metadata`` where the format allows.

    Raises:
        ValueError: unknown format (the message lists the choices).
    """
    fmt = str(fmt).lower().lstrip(".")
    if fmt not in MESH_FORMATS:
        raise ValueError(f"unknown mesh format {fmt!r}; expected one of {list(MESH_FORMATS)}")
    from trimesh.exchange import gltf, obj, ply, stl

    meta = _provenance(mesh)
    if fmt == "glb":
        # trimesh writes mesh.metadata into the glTF mesh "extras" (and reads it back into .metadata)
        return bytes(gltf.export_glb(mesh))
    if fmt == "ply":
        return _ply_with_comments(ply.export_ply(mesh, encoding="binary"), meta)
    if fmt == "obj":
        lines = ["NEMSim surface mesh"] + [f"{k}: {json.dumps(v, default=str)}" for k, v in meta.items()]
        header = "\n# ".join(line.replace("\n", " ") for line in lines)
        text = obj.export_obj(
            mesh, include_normals=False, include_color=False, include_texture=False, header=header
        )
        return text.encode("utf-8")
    data = bytearray(stl.export_stl(mesh))
    # binary STL: 80-byte free header (must not start with "solid", or readers take it for ASCII)
    summary = "NEMSim " + " ".join(f"{k}={v}" for k, v in meta.items() if isinstance(v, (str, int, float)))
    data[:80] = summary.encode("ascii", errors="replace")[:80].ljust(80, b" ")
    return bytes(data)
