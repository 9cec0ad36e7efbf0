"""GLB with ``EXT_meshopt_compression`` and ``KHR_mesh_quantization``: the phone model for viewers that decode
meshopt (three.js, model-viewer, Babylon.js, gltfpack's) without Draco's WASM module.

Layout: positions quantized to uint16 over the mesh's bounding box (the node's translation and scale map them back
to metres, so the scene is the same as :func:`engine.export.glb.to_glb`'s), normals as normalized int8, each padded
to a 4-byte vertex; indices in the index codec's triangle mode. Vertices are put in the order the reordered
triangles first use them (vertex cache, then fetch order), which is what makes the codec's deltas small. Every
compressed view has an uncompressed fallback view into a buffer without data (``fallback: true``), as the extension
specifies, and both extensions are required. Vertex codec version 0 (the only one EXT_meshopt_compression allows).

Needs the ``meshoptimizer`` package (PyPI), a binding of the C++ library's codecs.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.export.glb import (
    ARRAY_BUFFER,
    ELEMENT_ARRAY_BUFFER,
    TRIANGLES,
    UNSIGNED_INT,
    UNSIGNED_SHORT,
    base_document,
    gltf_mesh,
    index_type,
    pack_glb,
)

BYTE = 5120
EXT = "EXT_meshopt_compression"
QUANT = "KHR_mesh_quantization"
QMAX = 65535


def _meshopt() -> Any:
    try:
        import meshoptimizer
    except ImportError as exc:  # pragma: no cover - a dependency of the project
        raise ImportError("the meshopt GLB needs the meshoptimizer package: pip install meshoptimizer") from exc
    return meshoptimizer


def load_native() -> None:
    """Import meshoptimizer's native library now: ``engine.export.files`` calls it when the exporter is looked up, on
    the thread that then starts the threads that encode (a first load from two threads at once can deadlock)."""
    _meshopt()


def _fetch_order(tris: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """``(order, new_tris)``: vertices in the order the triangles first use them (unused ones dropped)."""
    flat = tris.ravel()
    used, first = np.unique(flat, return_index=True)
    order = used[np.argsort(first, kind="stable")]
    remap = np.empty(int(flat.max()) + 1, dtype=np.int64)
    remap[order] = np.arange(len(order))
    return order, remap[tris]


def to_meshopt_glb(
    vertices_zyx_mm: npt.ArrayLike,
    faces: npt.ArrayLike,
    normals_zyx: npt.ArrayLike | None = None,
    *,
    name: str = "bone",
) -> bytes:
    """Encode a mesh as a meshopt-compressed, quantized GLB (metres, +Y up, as :func:`~engine.export.glb.to_glb`).

    Args:
        vertices_zyx_mm: (V, 3) vertices in (z, y, x) order, mm.
        faces: (F, 3) vertex indices (outward with vertices in (x, y, z) order).
        normals_zyx: optional (V, 3) normals in (z, y, x) order; area-weighted vertex normals when None.
        name: the scene, node and mesh name.

    Returns:
        The GLB file's bytes.

    Raises:
        InputError: an empty or malformed mesh.
    """
    mo = _meshopt()
    positions, normals, tris = gltf_mesh(vertices_zyx_mm, faces, normals_zyx)
    cached = np.empty(tris.size, dtype=np.uint32)
    mo.optimize_vertex_cache(cached, tris.astype(np.uint32).ravel(), tris.size, len(positions))
    order, tris = _fetch_order(cached.astype(np.int64).reshape(-1, 3))
    positions, normals = positions[order], normals[order]

    lo, hi = positions.min(axis=0), positions.max(axis=0)
    scale = np.where(hi > lo, (hi - lo) / QMAX, 1.0)
    qpos = np.zeros((len(positions), 4), dtype=np.uint16)
    qpos[:, :3] = np.rint((positions - lo) / scale).clip(0, QMAX)
    qnrm = np.zeros((len(normals), 4), dtype=np.int8)
    qnrm[:, :3] = np.rint(normals * 127.0).clip(-127, 127)
    index_ctype, index_dtype = index_type(len(positions))
    indices = tris.astype(index_dtype).ravel()

    mo.encode_vertex_version(0)
    mo.encode_index_version(1)
    streams = [
        (mo.encode_vertex_buffer(qpos, len(qpos), 8), qpos.nbytes, 8, len(qpos), "ATTRIBUTES", ARRAY_BUFFER),
        (mo.encode_vertex_buffer(qnrm, len(qnrm), 4), qnrm.nbytes, 4, len(qnrm), "ATTRIBUTES", ARRAY_BUFFER),
        (mo.encode_index_buffer(indices, len(indices), len(positions)), indices.nbytes, indices.itemsize,
         len(indices), "TRIANGLES", ELEMENT_ARRAY_BUFFER),
    ]  # fmt: skip
    views, chunks, offset, fallback = [], [], 0, 0
    for data, raw_len, stride, count, mode, target in streams:
        ext = {"buffer": 0, "byteOffset": offset, "byteLength": len(data), "byteStride": stride, "count": count}
        view: dict[str, Any] = {"buffer": 1, "byteOffset": fallback, "byteLength": raw_len, "target": target}
        if target == ARRAY_BUFFER:
            view["byteStride"] = stride
        view["extensions"] = {EXT: {**ext, "mode": mode}}
        views.append(view)
        chunks.append(bytes(data) + b"\x00" * (-len(data) % 4))
        offset += len(chunks[-1])
        fallback += raw_len + (-raw_len % 4)
    binary = b"".join(chunks)
    accessors = [
        {"bufferView": 0, "componentType": UNSIGNED_SHORT, "count": len(qpos), "type": "VEC3",
         "min": [int(v) for v in qpos[:, :3].min(axis=0)], "max": [int(v) for v in qpos[:, :3].max(axis=0)]},
        {"bufferView": 1, "componentType": BYTE, "normalized": True, "count": len(qnrm), "type": "VEC3"},
        {"bufferView": 2, "componentType": index_ctype, "count": len(indices), "type": "SCALAR"},
    ]  # fmt: skip
    primitive = {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2, "material": 0, "mode": TRIANGLES}
    document = base_document(name, primitive, accessors)
    document["nodes"][0].update(translation=[float(v) for v in lo], scale=[float(v) for v in scale])
    document["bufferViews"] = views
    document["buffers"] = [
        {"byteLength": len(binary)},
        {"byteLength": fallback, "extensions": {EXT: {"fallback": True}}},
    ]
    document["extensionsUsed"] = [EXT, QUANT]
    document["extensionsRequired"] = [EXT, QUANT]
    return pack_glb(document, binary)


def read_meshopt_glb(data: bytes) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float32], npt.NDArray[np.int64]]:
    """Decode what :func:`to_meshopt_glb` wrote (with the library's decoders): positions in metres in the glTF
    frame (node transform applied), unit normals and (F, 3) triangles.

    Raises:
        ValueError: not such a GLB.
    """
    mo = _meshopt()
    if data[:4] != b"glTF":
        raise ValueError("Expected GLB bytes starting with 'glTF'")
    json_len = int.from_bytes(data[12:16], "little")
    doc = json.loads(data[20 : 20 + json_len])
    binary = data[20 + json_len + 8 :]
    if EXT not in doc.get("extensionsRequired", []):
        raise ValueError(f"Expected a GLB that requires {EXT}")

    def stream(i: int) -> tuple[bytes, dict[str, Any]]:
        ext = doc["bufferViews"][doc["accessors"][i]["bufferView"]]["extensions"][EXT]
        return binary[ext["byteOffset"] : ext["byteOffset"] + ext["byteLength"]], ext

    raw, ext = stream(0)
    qpos = np.ascontiguousarray(mo.decode_vertex_buffer(ext["count"], 8, raw)).view(np.uint16).reshape(-1, 4)[:, :3]
    raw, ext = stream(1)
    qnrm = np.ascontiguousarray(mo.decode_vertex_buffer(ext["count"], 4, raw)).view(np.int8).reshape(-1, 4)[:, :3]
    raw, ext = stream(2)
    size = {UNSIGNED_SHORT: 2, UNSIGNED_INT: 4}[doc["accessors"][2]["componentType"]]
    decoded = np.ascontiguousarray(mo.decode_index_buffer(ext["count"], size, raw))
    if decoded.dtype.itemsize != size:  # some builds hand back the raw bytes in a wider array
        decoded = decoded.view(np.uint16 if size == 2 else np.uint32)[: ext["count"]]
    tris = decoded.astype(np.int64).reshape(-1, 3)
    node = doc["nodes"][0]
    positions = qpos.astype(np.float64) * np.array(node["scale"]) + np.array(node["translation"])
    return positions, qnrm.astype(np.float32) / 127.0, tris
