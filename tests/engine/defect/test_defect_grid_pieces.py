"""The defect's own pieces and neighbourhoods are scipy's: ``grid.label_voxels`` (the 26-connected pieces of a few
voxels, from their touching pairs, or by scipy over their box where they are dense) numbers them as
``scipy.ndimage.label`` does, and ``grid.touching`` (a voxel's step along each axis in turn) is ``binary_dilation``
with the 3 x 3 x 3 cube, on random volumes of every density and thin shapes (an axis of one voxel), where pieces
wrap around, meet only at corners, and touch the array's borders."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage as ndi

from engine.defect.grid import CONNECTIVITY, label_voxels, touching


def _volumes(seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(120):
        shape = tuple(int(v) for v in rng.integers(1, 13, 3))
        out.append(rng.random(shape) < rng.uniform(0.0, 0.6))
    corners = np.zeros((4, 4, 4), dtype=bool)  # pieces that meet only at a corner or an edge: one piece
    corners[0, 0, 0] = corners[1, 1, 1] = corners[2, 2, 1] = corners[3, 3, 2] = True
    out.append(corners)
    out.append(np.zeros((3, 5, 2), dtype=bool))
    out.append(np.ones((2, 3, 4), dtype=bool))
    return out


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("way", ["pairs", "box"])
def test_the_pieces_of_a_few_voxels_are_scipys_numbered_alike(seed: int, way: str, monkeypatch) -> None:
    import engine.defect.grid as grid

    # the graph of touching pairs for sparse voxels, scipy's pass over their box for dense ones: both ways, always
    monkeypatch.setattr(grid, "DENSE_SHARE", 0 if way == "pairs" else 10**9)
    for vol in _volumes(seed):
        want, n = ndi.label(vol, structure=CONNECTIVITY)
        flat = np.flatnonzero(vol)
        got, m = label_voxels(flat, vol.shape)
        assert m == n
        np.testing.assert_array_equal(got, want.reshape(-1)[flat])
    one = np.zeros((4, 4, 4), dtype=bool)
    one[[0, 1, 2, 3], [0, 1, 2, 3], [0, 1, 1, 2]] = True  # a chain of corners and edges
    assert label_voxels(np.flatnonzero(one), one.shape)[1] == 1


@pytest.mark.parametrize("seed", [2, 3])
def test_the_voxels_touching_a_mask_are_its_dilation_by_the_cube(seed: int) -> None:
    for vol in _volumes(seed):
        sparse = vol & (np.random.default_rng(seed).random(vol.shape) < 0.2)
        for mask in (vol, sparse):
            np.testing.assert_array_equal(touching(mask), ndi.binary_dilation(mask, structure=CONNECTIVITY))
            assert touching(mask) is not mask
