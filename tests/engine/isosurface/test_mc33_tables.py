"""Lookup-table invariants: the committed tables are what the generator derives, and every entry is sound."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from engine.isosurface import _make_mc33_tables as gen
from engine.isosurface import mc33_tables as tables


def test_committed_tables_match_the_generator():
    committed = Path(tables.__file__).read_text()
    assert committed == gen.render_module(), "run: python -m engine.isosurface._make_mc33_tables"


def test_every_key_is_covered_and_supported():
    assert tables.UNSUPPORTED == ()
    keys = np.asarray(tables.KEYS)
    assert len(np.unique(keys)) == len(keys)
    configs = keys & 255
    assert set(configs.tolist()) == set(range(256))
    # every ambiguous-face assignment of every configuration has an entry with no body join
    for config in range(256):
        n_amb = len(gen.ambiguous_faces(config))
        plain = keys[(configs == config) & ((keys >> 14) == 0)]
        assert len(plain) == 2**n_amb


def test_triangulations_are_closed_on_the_loops():
    """Each entry: triangles reference cut edges or its own interior vertices; boundary = contour loops."""
    tri = np.asarray(tables.TRIANGLES).reshape(-1, 3)
    for key, tid in zip(tables.KEYS, tables.TRI_ID, strict=True):
        config = key & 255
        t = tri[tables.TRI_OFFSET[tid] : tables.TRI_OFFSET[tid] + tables.TRI_COUNT[tid]]
        cut = {e for e, (a, b) in enumerate(gen.EDGES) if ((config >> a) & 1) != ((config >> b) & 1)}
        used_edges = {int(v) for v in t.ravel() if v < 12}
        assert used_edges == cut, key
        n_int = tables.IVERT_COUNT[tid]
        assert {int(v) for v in t.ravel() if v >= 12} == set(range(12, 12 + n_int))
        i0 = tables.IVERT_OFFSET[tid]
        w = np.asarray(tables.IVERT_WEIGHTS).reshape(-1, 12)[i0 : i0 + n_int]
        np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)
        assert set(np.nonzero(w)[1].tolist()) <= cut


def test_complement_and_orientation():
    """Swapping above/below and flipping every face decision reverses the orientation of the same surface."""
    tri = np.asarray(tables.TRIANGLES).reshape(-1, 3)
    lookup = dict(zip(tables.KEYS, tables.TRI_ID, strict=True))
    for config in range(1, 255):
        amb = gen.ambiguous_faces(config)
        facebits = sum(1 << f for f in amb[::2])
        flipped = sum(1 << f for f in amb if not (facebits >> f) & 1)
        a = lookup[config | facebits << 8]
        b = lookup[(255 ^ config) | flipped << 8]
        if tables.IVERT_COUNT[a] or tables.IVERT_COUNT[b]:
            continue
        ta = tri[tables.TRI_OFFSET[a] : tables.TRI_OFFSET[a] + tables.TRI_COUNT[a]]
        tb = tri[tables.TRI_OFFSET[b] : tables.TRI_OFFSET[b] + tables.TRI_COUNT[b]]
        edges_a = {(int(t[k]), int(t[(k + 1) % 3])) for t in ta for k in range(3)}
        edges_b = {(int(t[(k + 1) % 3]), int(t[k])) for t in tb for k in range(3)}
        loop_a = {e for e in edges_a if (e[1], e[0]) not in edges_a}
        loop_b = {e for e in edges_b if (e[1], e[0]) not in edges_b}
        assert loop_a == loop_b, config


def test_interior_vertices_of_an_entry_never_coincide():
    """Two interior vertices with the same edge weights would sit on one spot (a degenerate pinch that cleaning
    tools merge into a non-manifold vertex); every entry's interior vertices differ."""
    weights = np.asarray(tables.IVERT_WEIGHTS).reshape(-1, 12)
    for tid in range(len(tables.TRI_COUNT)):
        rows = weights[tables.IVERT_OFFSET[tid] : tables.IVERT_OFFSET[tid] + tables.IVERT_COUNT[tid]]
        assert len(np.unique(rows, axis=0)) == len(rows), tid
