"""STL export: header, face count, (x, y, z) order in mm, unit normals."""

from __future__ import annotations

import numpy as np

from engine.export import EXPORTERS
from engine.export.stl import to_stl


def test_stl_layout_and_axis_order():
    verts_zyx = np.array([[0, 0, 0], [0, 0, 2], [0, 3, 0], [5, 0, 0]], np.float32)
    faces = np.array([[0, 2, 1], [0, 1, 3]], np.int32)
    data = to_stl(verts_zyx, faces, header="test")
    assert data[:4] == b"test" and len(data) == 84 + 50 * 2
    assert int(np.frombuffer(data[80:84], "<u4")[0]) == 2
    rec = np.frombuffer(data[84:], dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    np.testing.assert_array_equal(rec["v"][0], [[0, 0, 0], [0, 3, 0], [2, 0, 0]])  # x, y, z
    np.testing.assert_allclose(rec["n"][0], [0, 0, -1])
    np.testing.assert_allclose(np.linalg.norm(rec["n"], axis=1), 1.0)
    assert EXPORTERS["stl"] is to_stl
