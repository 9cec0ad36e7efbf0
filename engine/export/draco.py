"""Binary glTF 2.0 with ``KHR_draco_mesh_compression`` (Draco via DracoPy).

Positions and normals go through the same axis mapping as ``engine.export.glb`` (scanner (x, y, z) mm ->
glTF (x, z, -y) m, a proper rotation), then into one Draco mesh that is the file's only buffer data. The extension is
required (no uncompressed fallback), so loaders without a Draco decoder refuse the file rather than show nothing.

DracoPy quirks handled here:

* Attribute unique ids are not fixed: with normals, DracoPy 2.2 gives NORMAL id 0 and POSITION id 1; without them,
  POSITION is id 0. The encoded buffer is therefore decoded once and the ids are read by attribute type.
* Draco drops degenerate faces and unused vertices and, unless ``preserve_order``, reorders (and may split)
  vertices, so the accessors' counts and the POSITION min/max come from the decoded mesh, as the extension
  requires them to describe the decompressed data.
* ``encode`` asserts that normals are float64 (float32 normals fail with "Normals must be float").
* Positions are quantised to ``quantization_bits`` over the largest extent of the bounding box: the error is at
  most half a step, ``extent / (2**bits - 1) / 2`` per axis (14 bits on a 300 mm bone: about 0.01 mm). Normals are
  quantised to ``normal_quantization_bits`` per component (not octahedral), so decoded normals are unit length only
  to about ``2**-bits``; None stores them as lossless floats.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import DracoPy
import numpy as np
import numpy.typing as npt

from engine.errors import InputError
from engine.export.glb import (
    FLOAT,
    TRIANGLES,
    Part,
    accessor_bounds,
    add_node,
    base_document,
    gltf_mesh,
    index_type,
    pack_glb,
    part_material,
)

EXTENSION = "KHR_draco_mesh_compression"


def _unique_id(mesh: Any, attribute_type: DracoPy.AttributeType) -> int:
    """The unique id of the decoded mesh's attribute of the given type."""
    for attribute in mesh.attributes:
        if attribute["attribute_type"] == int(attribute_type):
            return int(attribute["unique_id"])
    raise RuntimeError(f"Draco buffer has no {attribute_type.name} attribute")


def to_draco_glb(
    vertices_zyx_mm: npt.ArrayLike,
    faces: npt.ArrayLike,
    normals_zyx: npt.ArrayLike | None = None,
    *,
    name: str = "bone",
    quantization_bits: int = 14,
    normal_quantization_bits: int | None = 10,
    compression_level: int = 7,
    include_normals: bool = True,
    parts: Sequence[Part] = (),
) -> bytes:
    """Encode a mesh as Draco-compressed binary glTF 2.0 (metres, +Y up; axes as in ``engine.export.glb``).

    Args:
        vertices_zyx_mm: (V, 3) vertices in (z, y, x) order, mm (the engine's convention).
        faces: (F, 3) vertex indices, outward normals with vertices taken in (x, y, z) order.
        normals_zyx: optional (V, 3) per-vertex normals in (z, y, x) order; area-weighted vertex normals when
            None (and ``include_normals``).
        name: the scene, node and mesh name.
        quantization_bits: position quantisation, 1..30 (Draco's default for glTF pipelines is 11-14).
        normal_quantization_bits: normal quantisation, 1..30, or None for lossless float normals.
        compression_level: Draco's effort, 0..10 (higher: smaller and slower).
        include_normals: encode a NORMAL attribute; without it viewers compute flat or smooth normals themselves.
        parts: more meshes (``engine.export.glb.Part``), each its own Draco primitive, node and material.

    Returns:
        The GLB file's bytes.

    Raises:
        InputError: an empty or malformed mesh, or parameters out of range.
    """
    if not 1 <= quantization_bits <= 30:
        raise InputError(f"quantization_bits must be in 1..30, got {quantization_bits}")
    if normal_quantization_bits is not None and not 1 <= normal_quantization_bits <= 30:
        raise InputError(f"normal_quantization_bits must be in 1..30 or None, got {normal_quantization_bits}")
    if not 0 <= compression_level <= 10:
        raise InputError(f"compression_level must be in 0..10, got {compression_level}")
    settings = (quantization_bits, normal_quantization_bits if include_normals else None, compression_level)
    accessors: list[dict[str, Any]] = []
    blobs: list[bytes] = []
    primitive = _draco_primitive(vertices_zyx_mm, faces, normals_zyx, settings, accessors, blobs)
    document = base_document(name, primitive, accessors)
    for part in parts:
        document["materials"].append(part_material(part))
        prim = _draco_primitive(part.vertices_zyx_mm, part.faces, part.normals_zyx, settings, accessors, blobs)
        add_node(document, part.name, {**prim, "material": len(document["materials"]) - 1})
    document["extensionsUsed"] = [EXTENSION]
    document["extensionsRequired"] = [EXTENSION]
    views, offset = [], 0
    for blob in blobs:
        offset += -offset % 4
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(blob)})
        offset += len(blob)
    document["bufferViews"] = views
    binary = b"".join(blob + b"\x00" * (-len(blob) % 4) for blob in blobs[:-1]) + blobs[-1]
    document["buffers"] = [{"byteLength": len(binary)}]
    return pack_glb(document, binary)


def _draco_primitive(
    vertices_zyx_mm: npt.ArrayLike,
    faces: npt.ArrayLike,
    normals_zyx: npt.ArrayLike | None,
    settings: tuple[int, int | None, int],
    accessors: list[dict[str, Any]],
    blobs: list[bytes],
) -> dict[str, Any]:
    """Encode one mesh with Draco (``settings``: position bits, normal bits or None for no normals, compression
    level), appending its accessors and its encoded bytes (the next buffer view); returns its primitive."""
    bits, normal_bits, level = settings
    positions, unit_normals, tris = gltf_mesh(vertices_zyx_mm, faces, normals_zyx)
    normals = unit_normals.astype(np.float64) if normal_bits is not None else None
    encoded = DracoPy.encode(
        positions.astype(np.float32),
        tris.astype(np.uint32),
        quantization_bits=bits,
        compression_level=level,
        normals=normals,
        normal_quantization_bits=normal_bits,
    )
    decoded = DracoPy.decode(encoded)
    if decoded.faces is None or len(decoded.faces) == 0:
        raise InputError("the mesh has no non-degenerate faces to compress")
    points = np.asarray(decoded.points, dtype=np.float32)
    attribute_ids = {"POSITION": _unique_id(decoded, DracoPy.AttributeType.POSITION)}
    attributes = {"POSITION": len(accessors)}
    accessors.append({"componentType": FLOAT, "count": len(points), "type": "VEC3", **accessor_bounds(points)})
    if normals is not None:
        attribute_ids["NORMAL"] = _unique_id(decoded, DracoPy.AttributeType.NORMAL)
        attributes["NORMAL"] = len(accessors)
        accessors.append({"componentType": FLOAT, "count": len(points), "type": "VEC3"})
    index_ctype, _ = index_type(len(points))
    accessors.append({"componentType": index_ctype, "count": int(decoded.faces.size), "type": "SCALAR"})
    blobs.append(bytes(encoded))
    return {
        "attributes": attributes,
        "indices": len(accessors) - 1,
        "material": 0,
        "mode": TRIANGLES,
        "extensions": {EXTENSION: {"bufferView": len(blobs) - 1, "attributes": attribute_ids}},
    }
