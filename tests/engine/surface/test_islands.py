"""Island removal on synthetic multi-ball volumes with known volumes."""

from __future__ import annotations

import numpy as np
import pytest

from engine.isosurface import marching_cubes_33
from engine.surface.islands import remove_islands
from engine.surface.meshcheck import mesh_stats
from tests.engine.meshutil import assert_closed_manifold

RADII = (3.0, 6.0, 10.0)  # voxels, spacing 1 mm


@pytest.fixture(scope="module")
def balls() -> tuple[np.ndarray, np.ndarray]:
    z, y, x = np.mgrid[:24, :24, :64].astype(np.float32)
    field = np.full(z.shape, -1e3, np.float32)
    for cx, r in zip((6.0, 20.0, 44.0), RADII, strict=True):
        field = np.maximum(field, r - np.sqrt((z - 12) ** 2 + (y - 12) ** 2 + (x - cx) ** 2))
    return marching_cubes_33(field, 0.0, device="cpu", closed=True)


def _ball(r: float) -> float:
    return 4.0 / 3.0 * np.pi * r**3


def test_min_volume(balls: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = balls
    ov, of, info = remove_islands(v, f, min_volume_mm3=_ball(4.5))
    assert info["pieces_before"] == 3 and info["pieces_after"] == 2
    assert info["removed_volume_mm3"] == pytest.approx(_ball(3.0), rel=0.1)  # coarse r = 3 voxel ball
    assert_closed_manifold(ov, of)
    s = mesh_stats(ov, of)
    assert s["components"] == 2
    assert s["volume_mm3"] == pytest.approx(_ball(6.0) + _ball(10.0), rel=0.05)


def test_keep_largest(balls: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = balls
    ov, of, info = remove_islands(v, f, keep_largest=1)
    assert info["pieces_after"] == 1
    assert mesh_stats(ov, of)["volume_mm3"] == pytest.approx(_ball(10.0), rel=0.05)
    # both: min volume drops the small one, then keep 5 keeps the other two
    _, _, info = remove_islands(v, f, min_volume_mm3=_ball(4.5), keep_largest=5)
    assert info["pieces_after"] == 2


def test_noop_keeps_order(balls: tuple[np.ndarray, np.ndarray]) -> None:
    v, f = balls
    ov, of, info = remove_islands(v, f, min_volume_mm3=0.0)
    assert info["removed_pieces"] == 0
    np.testing.assert_array_equal(of, f)
    np.testing.assert_array_equal(ov, v)


def test_invalid() -> None:
    v = np.zeros((3, 3), np.float32)
    f = np.array([[0, 1, 2]], np.int32)
    with pytest.raises(ValueError, match="min_volume_mm3"):
        remove_islands(v, f, min_volume_mm3=-1.0)
    with pytest.raises(ValueError, match="keep_largest"):
        remove_islands(v, f, keep_largest=0)
