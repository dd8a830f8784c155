"""Surface meshes of one SDF channel, in nm, and their export to glb / ply / obj / stl / vtp.

Coordinates. The field is a padded, transposed (D, H, W) = (z, y, x) channel (index = native + 1).
Marching cubes (scikit-image, level 0, unit spacing) gives vertices in index coordinates; we undo the
padding (-1) and the transposition ((z, y, x) -> (x, y, z)), convert voxel-centre coordinates to nm with
the voxel spanning [i, i + 1) * voxel_nm and move the origin into ``nemsim.geometry.frame``'s frame: x, y
from the hole axis, z above the initial Si top (depth below it = -z). So the initial Si top of a scene
lies at z = 0, the hole axis at x = y = 0 and the box spans +-nx * voxel_nm / 2 laterally and
[-si_top, nz - si_top] * voxel_nm vertically; the padding voxels extend the surface by half a voxel beyond
the box so that it reaches the box faces. Faces are wound so that normals point out of the material
(towards increasing SDF, i.e. into vacuum). Every file states the frame (``metadata["frame"]``).

Provenance: ``metadata`` (a JSON-serializable dict) is stored in ``mesh.metadata`` and embedded where the
format allows it: glb mesh ``extras``, ply ``comment`` header lines (one ``key=json`` per line), an obj
``#`` comment header, the binary stl header (the frame in short, then what fits in 80 bytes), and in vtp
an XML comment (every entry, ``key: json``) plus ``FieldData`` (the numeric entries, one Float64 tuple
each, which ParaView lists in its information panel).

VTP is VTK's XML PolyData (``VTKFile`` version 1.0, ``header_type="UInt64"``), what ParaView and VTK
based tools (ViennaPS among them) read natively. It is written here with the standard library rather
than through the ``vtk`` package (a large dependency for one writer): points Float32, triangles as
Int64 ``connectivity`` / ``offsets``, point ``Normals`` and, when the mesh has vertex colours (the
surrogate-error meshes), an RGBA UInt8 ``colors`` array; arrays inline as base64 of the byte count
followed by the little-endian data, uncompressed.
"""

from __future__ import annotations

import base64
import json
import math
from typing import TYPE_CHECKING, Any, Literal
from xml.sax.saxutils import quoteattr

import numpy as np

from nemsim.geometry.frame import FRAME, FRAME_SHORT, box_corner_nm

if TYPE_CHECKING:
    import trimesh

    from nemsim.scenes import Scene

MeshFormat = Literal["glb", "ply", "obj", "stl", "vtp"]
MESH_FORMATS: tuple[str, ...] = ("glb", "ply", "obj", "stl", "vtp")
MEDIA_TYPES = {
    "glb": "model/gltf-binary",
    "ply": "application/octet-stream",
    "obj": "model/obj",
    "stl": "model/stl",
    "vtp": "application/xml",  # no registered type; VTK's files are XML
}


def surface_mesh(field: Any, scene: Scene, metadata: dict | None = None) -> trimesh.Trimesh:
    """Zero level set of one normalized SDF channel as a triangle mesh in nm, (x, y, z) in the frame.

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
    meta.setdefault("frame", FRAME)
    meta.setdefault("scene", scene.name)
    if not (float(f.min()) < 0.0 < float(f.max())):
        empty = np.zeros((0, 3))
        return trimesh.Trimesh(vertices=empty, faces=empty.astype(np.int64), metadata=meta)
    # 'ascent' winding in (z, y, x) index space becomes outward (towards increasing SDF) once the axis
    # order is reversed below (a mirror); checked on a sphere in tests/geometry/test_mesh.py
    verts, faces, _, _ = marching_cubes(
        f, level=0.0, spacing=(1.0, 1.0, 1.0), gradient_direction="ascent", allow_degenerate=False
    )
    # (V, 3): unpad, (z,y,x)->(x,y,z), centres -> nm from the box corner, then into the frame
    xyz = (verts[:, ::-1] - 1.0 + 0.5) * scene.voxel_nm + box_corner_nm(scene)
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


def _vtk_array(
    name: str, values: np.ndarray, vtk_type: str, components: int = 1, tuples: bool = False
) -> str:
    """One inline binary ``DataArray``: base64 of the UInt64 byte count followed by the data (one stream);
    ``tuples``: state the tuple count (``FieldData`` arrays need it, VTK reads them empty otherwise)."""
    raw = np.ascontiguousarray(values).tobytes()
    data = base64.b64encode(np.array([len(raw)], dtype="<u8").tobytes() + raw).decode("ascii")
    comps = f' NumberOfComponents="{components}"' if components > 1 else ""
    if tuples:
        comps += f' NumberOfTuples="{len(values) // components}"'
    return f'<DataArray type="{vtk_type}" Name={quoteattr(name)}{comps} format="binary">{data}</DataArray>'


def _xml_comment(text: str) -> str:
    """`text` as an XML comment (a comment may not hold "--" nor end in "-")."""
    return "<!-- " + text.replace("--", "- -").rstrip("-") + " -->"


def _vtp(mesh: trimesh.Trimesh, meta: dict) -> bytes:
    """VTK XML PolyData of a triangle mesh (module docstring), provenance in a comment and ``FieldData``."""
    verts = np.asarray(mesh.vertices, dtype="<f4").reshape(-1, 3)  # (V, 3) nm
    faces = np.asarray(mesh.faces, dtype="<i8").reshape(-1, 3)  # (F, 3)
    point_arrays = []
    if len(verts):
        point_arrays.append(_vtk_array("Normals", np.asarray(mesh.vertex_normals, dtype="<f4"), "Float32", 3))
        if getattr(mesh.visual, "kind", None) == "vertex":
            colours = np.asarray(mesh.visual.vertex_colors, dtype=np.uint8)  # type: ignore[union-attr]
            point_arrays.append(_vtk_array("colors", colours, "UInt8", 4))
    numeric = {
        k: float(v)
        for k, v in meta.items()
        if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
    }
    field_data = "".join(
        _vtk_array(k, np.array([v], dtype="<f8"), "Float64", tuples=True) for k, v in numeric.items()
    )
    lines = ["NEMSim surface mesh"] + [f"{k}: {json.dumps(v, default=str)}" for k, v in meta.items()]
    offsets = 3 * np.arange(1, len(faces) + 1, dtype="<i8")  # (F,) end of each triangle in connectivity
    parts = [
        '<?xml version="1.0"?>',
        _xml_comment("\n     ".join(line.replace("\n", " ") for line in lines)),
        '<VTKFile type="PolyData" version="1.0" byte_order="LittleEndian" header_type="UInt64">',
        "<PolyData>",
        f"<FieldData>{field_data}</FieldData>" if field_data else "",
        f'<Piece NumberOfPoints="{len(verts)}" NumberOfVerts="0" NumberOfLines="0" NumberOfStrips="0" '
        f'NumberOfPolys="{len(faces)}">',
        f'<PointData Normals="Normals">{"".join(point_arrays)}</PointData>' if point_arrays else "",
        f"<Points>{_vtk_array('Points', verts, 'Float32', 3)}</Points>",
        "<Polys>"
        + _vtk_array("connectivity", faces.reshape(-1), "Int64")
        + _vtk_array("offsets", offsets, "Int64")
        + "</Polys>",
        "</Piece>",
        "</PolyData>",
        "</VTKFile>",
    ]
    return ("\n".join(p for p in parts if p) + "\n").encode("utf-8")


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
    if fmt == "vtp":
        return _vtp(mesh, meta)
    data = bytearray(stl.export_stl(mesh))
    # binary STL: 80-byte free header (must not start with "solid", or readers take it for ASCII)
    # the frame first, in short: what is cut at 80 bytes is provenance, not the meaning of the coordinates
    rest = " ".join(f"{k}={v}" for k, v in meta.items() if isinstance(v, (str, int, float)) and k != "frame")
    summary = f"NEMSim {FRAME_SHORT}; {rest}"
    data[:80] = summary.encode("ascii", errors="replace")[:80].ljust(80, b" ")
    return bytes(data)
