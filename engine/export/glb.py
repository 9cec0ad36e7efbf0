"""Binary glTF 2.0 (GLB) writer: one mesh, one primitive, written by hand with ``struct``/``json``.

Axis convention (fixed): glTF is right-handed, +Y up, in metres. Scanner coordinates (x, y, z) in mm map to
glTF (X, Y, Z) in metres as

    X = +x * 0.001        (scanner x: patient's left in DICOM LPS)
    Y = +z * 0.001        (scanner z: the slice axis, usually the patient's long axis, superior in LPS)
    Z = -y * 0.001        (scanner y: posterior in LPS, so glTF +Z, toward the default camera, is anterior)

i.e. ``p_gltf = 0.001 * R @ (x, y, z)`` with ``R = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]``, a rotation by -90 degrees
about x with ``det(R) = +1``. Being a proper rotation (no mirror), it keeps triangle winding and outward normals
valid: faces stay counter-clockwise seen from outside, as glTF requires. Given vertices in the patient frame (LPS,
as ``engine.orient`` places them: DICOM from its headers, image stacks by ``OrientParams``), the model stands
upright (head up, +Y) and faces the viewer (+Z). This writer applies no translation; ``write_outputs`` centres
the mesh on its bounding box first (``engine.orient.export_meshes``), so AR placement is not offset.

The layout is: bufferView 0 = POSITION (float32 VEC3, with min/max), bufferView 1 = NORMAL (float32 VEC3, unit),
bufferView 2 = indices (uint16 when there are fewer than 65536 vertices, else uint32), one buffer in the BIN chunk,
the JSON chunk padded with spaces and the BIN chunk with zeros to 4 bytes.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from engine.errors import InputError

# rows: glTF X, Y, Z in terms of scanner (x, y, z)
GLTF_FROM_XYZ = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
MM_TO_M = 1e-3
GENERATOR = "bonemesh"

# glTF enums
ARRAY_BUFFER = 34962
ELEMENT_ARRAY_BUFFER = 34963
FLOAT = 5126
UNSIGNED_SHORT = 5123
UNSIGNED_INT = 5125
TRIANGLES = 4

_GLB_MAGIC = 0x46546C67  # "glTF"
_CHUNK_JSON = 0x4E4F534A  # "JSON"
_CHUNK_BIN = 0x004E4942  # "BIN\0"

BONE_MATERIAL: dict[str, Any] = {
    "name": "bone",
    "pbrMetallicRoughness": {"baseColorFactor": [0.89, 0.85, 0.79, 1.0], "metallicFactor": 0.0, "roughnessFactor": 0.6},
    "doubleSided": False,
}


# a part's default colour: the defect template, a clear blue beside the bone's ivory
TEMPLATE_RGBA = (0.23, 0.56, 0.93, 1.0)


@dataclass(frozen=True)
class Part:
    """A named, coloured mesh shown beside the model in a glTF file (its own node and material): the defect
    template, or one label of a segmentation. Engine order (z, y, x) mm, in the frame and centring of the model's
    own vertices."""

    name: str
    vertices_zyx_mm: Any
    faces: Any
    rgba: tuple[float, float, float, float] = TEMPLATE_RGBA
    normals_zyx: Any = None

    def moved(self, shift_zyx_mm: Sequence[float]) -> Part:
        """The part with ``shift_zyx_mm`` added to every vertex (e.g. the glTF files' centring)."""
        verts = np.asarray(self.vertices_zyx_mm, np.float64) + np.asarray(shift_zyx_mm, np.float64)
        return Part(self.name, verts, self.faces, self.rgba, self.normals_zyx)


def part_material(part: Part) -> dict[str, Any]:
    """A part's material: its colour, matte like the bone's."""
    return {
        "name": part.name,
        "pbrMetallicRoughness": {"baseColorFactor": list(part.rgba), "metallicFactor": 0.0, "roughnessFactor": 0.5},
        "doubleSided": False,
    }


def add_node(document: dict[str, Any], name: str, primitive: dict[str, Any]) -> None:
    """Append a one-primitive mesh to ``document`` as a node of its scene."""
    document["meshes"].append({"name": name, "primitives": [primitive]})
    document["nodes"].append({"name": name, "mesh": len(document["meshes"]) - 1})
    document["scenes"][0]["nodes"].append(len(document["nodes"]) - 1)


def add_parts(document: dict[str, Any], buffer: list[npt.NDArray[Any]], parts: Sequence[Part]) -> None:
    """Append each part (plain accessors: POSITION, NORMAL, indices) to a document of :func:`mesh_document`, its
    arrays to the buffer's parts, every view 4-byte aligned.

    Raises:
        InputError: an empty or malformed part.
    """
    offset = int(document["buffers"][0]["byteLength"])
    for part in parts:
        pad = -offset % 4  # uint16 indices before may end mid-word
        if pad:
            buffer.append(np.zeros(pad, np.uint8))
            offset += pad
        positions, normals, tris = gltf_mesh(part.vertices_zyx_mm, part.faces, part.normals_zyx)
        index_ctype, index_dtype = index_type(len(positions))
        arrays = [positions.astype(np.float32), normals, np.ascontiguousarray(tris, index_dtype)]
        first = len(document["accessors"])
        for data, target in zip(arrays, (ARRAY_BUFFER, ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER), strict=True):
            document["bufferViews"].append(
                {"buffer": 0, "byteOffset": offset, "byteLength": data.nbytes, "target": target}
            )
            buffer.append(data)
            offset += data.nbytes
        views = len(document["bufferViews"])
        document["accessors"] += [
            {"bufferView": views - 3, "componentType": FLOAT, "count": len(positions), "type": "VEC3",
             **accessor_bounds(arrays[0])},
            {"bufferView": views - 2, "componentType": FLOAT, "count": len(positions), "type": "VEC3"},
            {"bufferView": views - 1, "componentType": index_ctype, "count": arrays[2].size, "type": "SCALAR"},
        ]  # fmt: skip
        document["materials"].append(part_material(part))
        primitive = {
            "attributes": {"POSITION": first, "NORMAL": first + 1},
            "indices": first + 2,
            "material": len(document["materials"]) - 1,
            "mode": TRIANGLES,
        }
        add_node(document, part.name, primitive)
    document["buffers"][0]["byteLength"] = offset


def check_mesh(
    vertices_zyx_mm: npt.ArrayLike, faces: npt.ArrayLike, normals_zyx: npt.ArrayLike | None = None
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64], npt.NDArray[np.float64] | None]:
    """Validate an engine mesh and return it as float64/int64 arrays (normals None if not given).

    Raises:
        InputError: wrong shapes, an empty mesh, non-finite values or indices out of range.
    """
    verts = np.asarray(vertices_zyx_mm, dtype=np.float64)
    tris = np.asarray(faces, dtype=np.int64)
    if verts.ndim != 2 or verts.shape[1] != 3 or tris.ndim != 2 or tris.shape[1] != 3:
        raise InputError(f"expected (V, 3) vertices and (F, 3) faces, got {verts.shape} and {tris.shape}")
    if len(verts) == 0 or len(tris) == 0:
        raise InputError("cannot export an empty mesh to glTF (no vertices or no faces)")
    if not np.isfinite(verts).all():
        raise InputError("mesh vertices contain NaN or infinite values")
    if tris.min() < 0 or tris.max() >= len(verts):
        raise InputError(f"face indices out of range [0, {len(verts)})")
    if len(verts) > 2**32 - 1:
        raise InputError("too many vertices for uint32 indices")
    norms = None
    if normals_zyx is not None:
        norms = np.asarray(normals_zyx, dtype=np.float64)
        if norms.shape != verts.shape:
            raise InputError(f"normals shape {norms.shape} does not match vertices {verts.shape}")
    return verts, tris, norms


def zyx_to_gltf(vectors_zyx: npt.NDArray[np.floating], scale: float = 1.0) -> npt.NDArray[np.float64]:
    """Map (z, y, x) engine vectors to the glTF frame (see the module docstring), times ``scale``."""
    xyz = np.asarray(vectors_zyx, dtype=np.float64)[:, ::-1]
    return (xyz @ GLTF_FROM_XYZ.T) * scale


def gltf_mesh(
    vertices_zyx_mm: npt.ArrayLike, faces: npt.ArrayLike, normals_zyx: npt.ArrayLike | None = None
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """An engine mesh in the glTF frame, as every viewer exporter starts: validated (:func:`check_mesh`), positions
    in metres (float64), unit normals (the given ones rotated, else area-weighted: :func:`vertex_normals`), and the
    triangles.

    Raises:
        InputError: as :func:`check_mesh`.
    """
    verts, tris, norms = check_mesh(vertices_zyx_mm, faces, normals_zyx)
    positions = zyx_to_gltf(verts, MM_TO_M)
    return positions, vertex_normals(positions, tris, None if norms is None else zyx_to_gltf(norms)), tris


def vertex_normals(
    positions: npt.NDArray[np.floating], faces: npt.NDArray[np.integer], normals: npt.NDArray[np.floating] | None = None
) -> npt.NDArray[np.float32]:
    """Unit per-vertex normals in the frame of ``positions``.

    Given ``normals`` (same frame) are normalised; vertices whose given normal has zero length or is not finite,
    and all vertices when none are given, get the area-weighted mean of their faces' normals. A vertex that still
    has none (only in zero-area faces) gets +Y, so every normal is unit length as glTF requires.

    Args:
        positions: (V, 3) vertex positions.
        faces: (F, 3) counter-clockwise (outward) triangles.
        normals: optional (V, 3) normals to normalise.

    Returns:
        (V, 3) float32 unit normals.
    """
    pos = np.asarray(positions, dtype=np.float64)
    out = np.zeros_like(pos) if normals is None else np.nan_to_num(np.asarray(normals, dtype=np.float64), nan=0.0)
    length = np.linalg.norm(out, axis=1)
    missing = ~(length > 0) | ~np.isfinite(length)
    if missing.any():
        tri = pos[faces]
        area_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
        summed = np.zeros_like(pos)
        for k in range(3):
            np.add.at(summed, faces[:, k], area_normal)
        out[missing] = summed[missing]
        length = np.linalg.norm(out, axis=1)
    unit = np.divide(out, length[:, None], out=np.zeros_like(out), where=length[:, None] > 0)
    unit[~(length > 0)] = (0.0, 1.0, 0.0)
    return unit.astype(np.float32)


def index_type(vertex_count: int) -> tuple[int, type[np.unsignedinteger[Any]]]:
    """The index componentType and dtype: uint16 below 65536 vertices (65535 stays free as the restart value)."""
    return (UNSIGNED_SHORT, np.uint16) if vertex_count < 65536 else (UNSIGNED_INT, np.uint32)


def accessor_bounds(values: npt.NDArray[np.float32]) -> dict[str, list[float]]:
    """The ``min``/``max`` of an accessor, from the float32 values as stored."""
    return {"min": [float(v) for v in values.min(axis=0)], "max": [float(v) for v in values.max(axis=0)]}


def base_document(name: str, primitive: dict[str, Any], accessors: list[dict[str, Any]]) -> dict[str, Any]:
    """A glTF document with one scene, node, mesh (``primitive``) and the bone material; no buffers yet."""
    return {
        "asset": {"version": "2.0", "generator": GENERATOR},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0]}],
        "nodes": [{"name": name, "mesh": 0}],
        "meshes": [{"name": name, "primitives": [primitive]}],
        "materials": [dict(BONE_MATERIAL)],
        "accessors": accessors,
    }


def pack_glb(document: dict[str, Any], binary: bytes) -> bytes:
    """Assemble a GLB: 12-byte header, JSON chunk (space-padded), BIN chunk (zero-padded) if ``binary``.

    Args:
        document: the glTF JSON; its ``buffers[0].byteLength`` must be ``len(binary)`` (before padding).
        binary: the buffer's bytes.

    Returns:
        The GLB file's bytes; every chunk length is a multiple of 4.
    """
    pad = b"\x00" * (-len(binary) % 4)
    return glb_head(document, len(binary)) + binary + pad


def glb_head(document: dict[str, Any], binary_length: int) -> bytes:
    """The GLB's bytes up to its BIN chunk's data: header, JSON chunk, and the BIN chunk's header when
    ``binary_length`` > 0 (the data then follow, zero-padded to 4 bytes)."""
    text = json.dumps(document, separators=(",", ":"), ensure_ascii=True).encode("utf-8")
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<II", len(text), _CHUNK_JSON) + text
    padded = binary_length + (-binary_length % 4)
    total = 12 + len(chunks) + (8 + padded if binary_length else 0)
    head = struct.pack("<III", _GLB_MAGIC, 2, total) + chunks
    if binary_length:
        head += struct.pack("<II", padded, _CHUNK_BIN)
    return head


def mesh_document(
    positions: npt.NDArray[np.float32],
    normals: npt.NDArray[np.float32],
    tris: npt.NDArray[np.integer],
    name: str = "bone",
    bounds: dict[str, list[float]] | None = None,
) -> tuple[dict[str, Any], list[npt.NDArray[Any]]]:
    """The glTF document of one mesh already in the glTF frame, and its buffer's parts in order (POSITION, NORMAL,
    indices); ``bounds``: the positions' accessor ``min``/``max`` when already known."""
    index_ctype, index_dtype = index_type(len(positions))
    parts = [
        np.ascontiguousarray(positions, np.float32),
        np.ascontiguousarray(normals, np.float32),
        np.ascontiguousarray(
            tris.view(np.uint32) if tris.dtype == np.int32 and index_dtype is np.uint32 else tris, index_dtype
        ),
    ]
    views, offset = [], 0
    for data, target in zip(parts, (ARRAY_BUFFER, ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER), strict=True):
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": data.nbytes, "target": target})
        offset += data.nbytes  # float32 parts come first, so every view starts 4-byte aligned
    accessors = [
        {
            "bufferView": 0,
            "componentType": FLOAT,
            "count": len(positions),
            "type": "VEC3",
            **(bounds or accessor_bounds(parts[0])),
        },
        {"bufferView": 1, "componentType": FLOAT, "count": len(normals), "type": "VEC3"},
        {"bufferView": 2, "componentType": index_ctype, "count": parts[2].size, "type": "SCALAR"},
    ]
    primitive = {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2, "material": 0, "mode": TRIANGLES}
    document = base_document(name, primitive, accessors)
    document["bufferViews"] = views
    document["buffers"] = [{"byteLength": offset}]
    return document, parts


def write_glb(out: BinaryIO, document: dict[str, Any], parts: list[npt.NDArray[Any]]) -> int:
    """Write a GLB to an open binary file from its document and buffer parts, without joining them in memory;
    returns the bytes written."""
    length = sum(p.nbytes for p in parts)
    head = glb_head(document, length)
    out.write(head)
    for p in parts:
        out.write(memoryview(p).cast("B"))
    out.write(b"\x00" * (-length % 4))
    return len(head) + length + (-length % 4)


def to_glb(
    vertices_zyx_mm: npt.ArrayLike,
    faces: npt.ArrayLike,
    normals_zyx: npt.ArrayLike | None = None,
    *,
    name: str = "bone",
    parts: Sequence[Part] = (),
) -> bytes:
    """Encode a mesh as binary glTF 2.0 (metres, +Y up; axes as in the module docstring), with ``parts`` (each its
    own named, coloured node) beside it.

    Args:
        vertices_zyx_mm: (V, 3) vertices in (z, y, x) order, mm (the engine's convention).
        faces: (F, 3) vertex indices, outward normals with vertices taken in (x, y, z) order.
        normals_zyx: optional (V, 3) per-vertex normals in (z, y, x) order; area-weighted vertex normals when
            None. They are rotated like the positions and normalised.
        name: the scene, node and mesh name.
        parts: more meshes, each its own node and material (``Part``: engine order, same frame as the mesh).

    Returns:
        The GLB file's bytes.

    Raises:
        InputError: an empty or malformed mesh or part.
    """
    positions, normals, tris = gltf_mesh(vertices_zyx_mm, faces, normals_zyx)
    document, buffer = mesh_document(positions, normals, tris, name)
    add_parts(document, buffer, parts)
    return pack_glb(document, b"".join(p.tobytes() for p in buffer))


def read_glb(data: bytes) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32], npt.NDArray[np.uint32]]:
    """Decode the POSITION, NORMAL and index arrays of a one-primitive GLB as :func:`to_glb` writes it.

    Returns:
        (positions (V, 3) float32 in metres, normals (V, 3) float32, triangles (F, 3) uint32), in the glTF frame.

    Raises:
        ValueError: not a GLB of that shape (Draco-compressed files included).
    """
    if len(data) < 20 or data[:4] != b"glTF":
        raise ValueError("Expected GLB bytes starting with 'glTF'")
    json_len = int.from_bytes(data[12:16], "little")
    doc = json.loads(data[20 : 20 + json_len])
    bin_start = 20 + json_len + 8
    prim = doc["meshes"][0]["primitives"][0]
    if "extensions" in prim:
        raise ValueError(f"Expected an uncompressed primitive, got extensions {sorted(prim['extensions'])}")
    dtypes = {FLOAT: np.float32, UNSIGNED_SHORT: np.uint16, UNSIGNED_INT: np.uint32}

    def accessor(i: int) -> npt.NDArray[Any]:
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        n = acc["count"] * (3 if acc["type"] == "VEC3" else 1)
        arr = np.frombuffer(data, dtypes[acc["componentType"]], n, bin_start + view.get("byteOffset", 0))
        return arr.reshape(-1, 3)

    pos = accessor(prim["attributes"]["POSITION"])
    nrm = accessor(prim["attributes"]["NORMAL"])
    return pos, nrm, accessor(prim["indices"]).astype(np.uint32)
