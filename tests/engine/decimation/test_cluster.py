"""Quadric vertex clustering (the viewing copies' last resort): budget met closely, valid faces, shape kept."""

from __future__ import annotations

import numpy as np
import pytest

from engine.isosurface import marching_cubes_33


@pytest.fixture(scope="module")
def plate() -> tuple[np.ndarray, np.ndarray]:
    """A perforated plate: one piece with 64 tunnels, which the topology guard cannot decimate far."""
    z, y, x = np.indices((16, 60, 60), dtype=np.float32)
    slab = np.minimum(3.5 - np.abs(z - 7.5), 26 - np.maximum(np.abs(y - 29.5), np.abs(x - 29.5)))
    holes = 1.8 - np.hypot((y - 29.5 + 24) % 6 - 3, (x - 29.5 + 24) % 6 - 3)
    holes[:, np.abs(np.arange(60) - 29.5) > 23, :] = -1
    holes[:, :, np.abs(np.arange(60) - 29.5) > 23] = -1
    return marching_cubes_33(np.minimum(slab, -holes), 0.0, spacing=(0.5, 0.5, 0.5), device="cpu", closed=True)


def _run(v: np.ndarray, f: np.ndarray, budget: int, device: str) -> tuple[np.ndarray, np.ndarray, dict]:
    import warp as wp

    from engine.decimation.cluster import cluster_device

    with wp.ScopedDevice(device):
        p, t, info = cluster_device(wp.array(v, dtype=wp.vec3), wp.array(f, dtype=wp.vec3i), budget)
        return p.numpy(), t.numpy(), info


@pytest.mark.parametrize("budget", [3000, 800])
def test_budget_met_closely_with_valid_faces(plate, budget, device) -> None:
    v, f = plate
    cv, cf, info = _run(v, f, budget, device)
    assert 0.6 * budget <= len(cf) <= budget, info
    assert (cf[:, 0] != cf[:, 1]).all() and (cf[:, 1] != cf[:, 2]).all() and (cf[:, 0] != cf[:, 2]).all()
    assert len(np.unique(np.sort(cf, axis=1), axis=0)) == len(cf)  # no face twice
    assert np.bincount(cf.ravel(), minlength=len(cv)).min() > 0  # no unused vertex
    lo, hi = v.min(axis=0), v.max(axis=0)
    assert (cv >= lo - 1e-4).all() and (cv <= hi + 1e-4).all()  # inside the model's box


def test_shape_kept(plate, device) -> None:
    """Every clustered vertex lies near the original surface (within a cell)."""
    from engine.paper.metrics import SurfaceQuery

    v, f = plate
    cv, _, info = _run(v, f, 3000, device)
    d = SurfaceQuery(v, f, device).distances(cv)
    assert d.max() <= info["cell_mm"] * np.sqrt(3)


def test_deterministic(plate, device) -> None:
    v, f = plate
    a = _run(v, f, 1500, device)
    b = _run(v, f, 1500, device)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_one_preparation_serves_several_budgets(plate, device) -> None:
    """The AR copy reuses the phone copy's clustering: both within budget and close to it, few new trials."""
    import warp as wp

    from engine.decimation.cluster import SEARCH_STEPS, Clustering

    v, f = plate
    with wp.ScopedDevice(device):
        prepared = Clustering(wp.array(v, dtype=wp.vec3), wp.array(f, dtype=wp.vec3i))
        _, big, first = prepared.copy(3000)
        p, t, second = prepared.copy(1200)
        assert 0.6 * 3000 <= len(big) <= 3000 and 0.6 * 1200 <= len(t) <= 1200
        assert second["trials"] < SEARCH_STEPS and second["input_faces"] == first["input_faces"] == len(f)
        assert len(p) == len(np.unique(t.numpy())) and second["faces"] == len(t)


def test_over_budget_with_the_largest_cell_returns_it(plate, device) -> None:
    """A budget no cell size can meet gives the coarsest clustering (a quarter of the diagonal), over budget."""
    v, f = plate
    _, cf, info = _run(v, f, 1, device)
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    assert len(cf) > 1 and info["cell_mm"] == pytest.approx(diag / 4, rel=1e-6)


def test_piece_census(plate, device) -> None:
    """Pieces largest first with their faces and vertices (as the host labels count them); the topology floor of
    a closed piece is 8 - 2 X (the plate: 64 tunnels, 4 + 4 * 64 faces)."""
    import warp as wp

    from engine.decimation.cluster import piece_census
    from engine.surface.meshcheck import component_labels

    v, f = plate
    ball_v, ball_f = marching_cubes_33(
        5.0 - np.sqrt(((np.indices((12, 12, 12), dtype=np.float32) - 5.5) ** 2).sum(axis=0)), 0.0, device="cpu"
    )
    verts = np.vstack([ball_v + np.float32([40.0, 0.0, 0.0]), v]).astype(np.float32)
    faces = np.vstack([ball_f, f + len(ball_v)]).astype(np.int32)
    with wp.ScopedDevice(device):
        pieces = piece_census(wp.array(verts, dtype=wp.vec3), wp.array(faces, dtype=wp.vec3i))
    assert len(pieces) == component_labels(faces, len(verts))[0] == 2
    assert pieces.volume[0] > pieces.volume[1]  # the plate first
    assert list(pieces.faces) == [len(f), len(ball_f)] and list(pieces.vertices) == [len(v), len(ball_v)]
    assert pieces.floor(1) == 4 + 4 * 64 and pieces.floor(2) == 4 + 4 * 64 + 4
    assert pieces.fit(len(f) - 1) == 0 and pieces.fit(len(f)) == 1 and pieces.fit(len(faces)) == 2
