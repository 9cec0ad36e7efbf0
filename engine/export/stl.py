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
    (x, y, z) order, mm: ``engine.kernels.export.stl_facets``), a chunk at a time; returns the bytes written."""
    facets = np.ascontiguousarray(facets, dtype="<f4").reshape(-1, 12)
    out.write(stl_head(len(facets), header))
    buf = np.zeros((min(len(facets), _CHUNK), _FACET.itemsize), np.uint8)  # attribute bytes stay zero
    for lo in range(0, len(facets), _CHUNK):
        part = facets[lo : lo + _CHUNK]
        buf[: len(part), :48] = part.view(np.uint8).reshape(len(part), 48)
        out.write(memoryview(buf[: len(part)]).cast("B"))
    return 84 + _FACET.itemsize * len(facets)
