"""Binary STL writer (millimetres)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

_FACET = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])


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
    head = header.encode("ascii", "replace")[:80].ljust(80, b" ")
    return head + np.uint32(len(tri)).tobytes() + rec.tobytes()
