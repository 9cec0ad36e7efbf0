"""A piece's own mirror plane (``engine.defect.plane.ring_plane``, issue 42): the trilinear samples and their
gradient that its least squares steps on (``_trilinear``, against scipy's ``map_coordinates``), and the plane of a
volume made mirror-symmetric by construction, found again from a start turned and moved off it."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("layout", ["crop", "whole", "one slice"])
def test_the_trilinear_samples_are_scipys_and_their_gradient_its_slope(layout: str) -> None:
    from scipy import ndimage as ndi

    from engine.defect.plane import _trilinear

    rng = np.random.default_rng(3)
    data = rng.integers(0, 3000, (9, 12, 15)).astype(np.uint16)[1:8, 2:11, 3:14]  # a crop: not contiguous
    if layout != "crop":  # read through one flat index per corner
        data = np.ascontiguousarray(data[:1] if layout == "one slice" else data)
    at = rng.uniform(-1.5, np.asarray(data.shape) + 0.5, size=(4000, 3))  # some beyond every edge
    value, grad = _trilinear(data, at)
    want = ndi.map_coordinates(data, at.T, order=1, mode="nearest", output=np.float64)
    np.testing.assert_allclose(value, want, rtol=0, atol=1e-9)
    h = 1e-5
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        up = ndi.map_coordinates(data, (at + step).T, order=1, mode="nearest", output=np.float64)
        down = ndi.map_coordinates(data, (at - step).T, order=1, mode="nearest", output=np.float64)
        # within a cell the interpolant is linear along each axis: the central difference is its slope, but where
        # the step crosses a cell's face (the slope changes there)
        frac = at[:, axis] - np.floor(at[:, axis])
        inside = (frac > 2 * h) & (frac < 1 - 2 * h)
        np.testing.assert_allclose(grad[inside, axis], ((up - down) / (2 * h))[inside], rtol=0, atol=1e-4)
        beyond = (at[:, axis] < 0) | (at[:, axis] > data.shape[axis] - 1)
        assert np.all(grad[beyond, axis] == 0.0)  # the edge's value beyond it: flat


def _turn(n: np.ndarray, deg: float, axis: np.ndarray) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    t = np.radians(deg)
    out = n * np.cos(t) + np.cross(axis, n) * np.sin(t) + axis * (axis @ n) * (1 - np.cos(t))
    return np.asarray(out / np.linalg.norm(out))


@pytest.mark.parametrize("start_turn_deg, start_move_mm", [(1.5, 1.0), (-1.0, -1.5)])
def test_the_plane_of_a_mirror_symmetric_volume_is_found_from_a_start_off_it(start_turn_deg, start_move_mm) -> None:
    """A volume that is its own mirror image across a plane turned 4 degrees off the grid's x axis (anisotropic
    voxels): blobs of bone on one side and their mirror images on the other. From a start turned by a degree or
    more and moved by a millimetre or more, the ring's plane is the volume's to 0.1 degree and 0.05 mm, and its
    residual the one left at the volume's own plane (the trilinear samples' error, not the plane's)."""
    from engine.defect.grid import Grid
    from engine.defect.plane import ring_plane

    shape, sp = (36, 44, 48), (1.6, 0.9, 0.8)  # z, y, x
    grid = Grid(shape, sp, np.eye(3), np.zeros(3), "test")
    xyz = grid.xyz(np.argwhere(np.ones(shape, dtype=bool)))
    normal = _turn(np.array([1.0, 0.0, 0.0]), 4.0, np.array([0.0, 0.3, 1.0]))
    offset = float(normal @ xyz.mean(axis=0)) + 0.7
    rng = np.random.default_rng(8)
    centres = xyz[rng.choice(len(xyz), 40, replace=False)]
    centres = centres[(centres @ normal - offset) > 2.0]  # blobs on one side of the plane
    mirrored = centres - 2.0 * ((centres @ normal - offset)[:, None]) * normal
    field = np.zeros(len(xyz))
    for c in np.concatenate([centres, mirrored]):
        field += 1500.0 * np.exp(-np.sum((xyz - c) ** 2, axis=1) / (2 * 3.0**2))
    data = (100.0 + field).reshape(shape).astype(np.float32)
    # the ring: the voxels where the bone fraction is neither nothing nor clipped (what moves the fit)
    ring = np.argwhere((data > 200.0) & (data < 1500.0))
    assert len(ring) > 1000
    start = _turn(normal, start_turn_deg, np.array([0.0, 1.0, 0.2]))
    n, d, rms = ring_plane(data, grid, start, offset + start_move_mm, ring, tissue=100.0, level=900.0)
    angle = float(np.degrees(np.arccos(min(1.0, abs(float(n @ normal))))))
    assert angle < 0.1
    assert abs(d - offset) < 0.05
    _, _, floor = ring_plane(data, grid, normal, offset, ring, tissue=100.0, level=900.0)
    assert rms <= 1.01 * floor
