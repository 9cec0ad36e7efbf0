"""Binary STL writer (millimetres)."""

from __future__ import annotations

from typing import BinaryIO

import numpy as np
import numpy.typing as npt

_FACET = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
_CHUNK = 1 << 20  # facets per write of write_stl


def to_stl(verts_zyx_mm: npt.NDArray[np.float32], faces: npt.NDArray[np.int32], header: str = "bonemesh") -> bytes:
    """Encode a mesh as binary STL.

    Args:
        verts_zyx_mm: (V, 3) vertices in (z, y, x) order, mm (the engine's convention).
        faces: (F, 3) vertex indices, oriented with outward normals in (x, y, z) order.
        header: text for the 80-byte header.

    Returns:
        The STL file's bytes, with vertices written in (x, y, z) order, in mm.
    """
    xyz = np.asarray(verts_zyx_mm, dtype=np.float32)[:, ::-1]
    tri = xyz[np.asarray(faces, dtype=np.int64)]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    rec = np.zeros(len(tri), dtype=_FACET)
    rec["normal"] = normal
    rec["v"] = tri
    return stl_head(len(tri), header) + rec.tobytes()


def stl_head(n_faces: int, header: str) -> bytes:
    """The 84 bytes before the facets: the header text (ASCII, 80 bytes) and the facet count."""
    return header.encode("ascii", "replace")[:80].ljust(80, b" ") + np.uint32(n_faces).tobytes()


def write_stl(out: BinaryIO, facets: npt.NDArray[np.float32], header: str = "bonemesh") -> int:
    """Write a binary STL to an open file from its facets' 12 floats each (unit normal, then the three corners, in
    (x, y, z) order, mm: ``engine.export.kernels.layout.stl_facets``), a chunk at a time; returns the bytes written."""
    facets = np.ascontiguousarray(facets, dtype="<f4").reshape(-1, 12)
    out.write(stl_head(len(facets), header))
    buf = np.zeros((min(len(facets), _CHUNK), _FACET.itemsize), np.uint8)  # attribute bytes stay zero
    for lo in range(0, len(facets), _CHUNK):
        part = facets[lo : lo + _CHUNK]
        buf[: len(part), :48] = part.view(np.uint8).reshape(len(part), 48)
        out.write(memoryview(buf[: len(part)]).cast("B"))
    return 84 + _FACET.itemsize * len(facets)


def from_stl(data: bytes) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int32]]:
    """Decode a binary STL (the inverse of :func:`to_stl`): shared vertices merged where bit-identical.

    Args:
        data: the file's bytes.

    Returns:
        (V, 3) float32 vertices in (z, y, x) order (mm, as written) and (F, 3) int32 faces.

    Raises:
        ValueError: not a binary STL (too short, or the size does not match the face count).
    """
    if len(data) < 84:
        raise ValueError(f"Expected a binary STL of at least 84 bytes, got {len(data)}")
    count = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    if len(data) != 84 + count * _FACET.itemsize:
        raise ValueError(f"Expected {84 + count * _FACET.itemsize} bytes for {count} facets, got {len(data)}")
    rec = np.frombuffer(data, dtype=_FACET, count=count, offset=84)
    corners = rec["v"].reshape(-1, 3)
    unique, inverse = np.unique(corners, axis=0, return_inverse=True)
    return (
        np.ascontiguousarray(unique[:, ::-1], dtype=np.float32),
        inverse.reshape(-1, 3).astype(np.int32),
    )
