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

    from engine.stages.cluster import cluster_device

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
    from engine.metrics import SurfaceQuery

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
