"""Pipeline stages owned by the pipeline: parameters, Gaussian, Laplacian smoothing, normals, iso choice, crop."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from engine.errors import InputError
from engine.isosurface import marching_cubes_33
from engine.level import choose_level
from engine.params import DecimateParams, IsoParams, PreprocessParams, ReconParams, SmoothParams
from engine.types import Volume
from engine.volume.preprocess import crop_volume, preprocess_volume
from tests.engine.meshutil import assert_closed_manifold, signed_volume, topology

pytestmark = pytest.mark.both_backends  # device tests run on Warp's CPU and on OpenCL (tests/conftest.py)


@pytest.fixture
def wp_device(device):
    from engine.device import resolve_device

    return resolve_device(device)


def ball_mesh(radius: float = 9.0, noise: float = 0.0):
    z, y, x = np.indices((28, 30, 32), dtype=np.float32)
    vol = radius - np.sqrt((z - 13.5) ** 2 + (y - 14.2) ** 2 + (x - 15.1) ** 2)
    if noise:
        vol += np.random.default_rng(0).normal(scale=noise, size=vol.shape).astype(np.float32)
    return marching_cubes_33(vol.astype(np.float32), 0.0, spacing=(1.2, 1.0, 0.8), device="cpu", closed=True)


# ------------------------------------------------------------------------------------------- params
def test_params_round_trip_through_json():
    p = ReconParams(
        preprocess=PreprocessParams(threshold=100.0, crop_zyx_mm=((0.0, 10.0), (1.0, 5.0), (2.0, 8.0))),
        iso=IsoParams(preset="bone", hu_offset=1024.0),
        decimate=DecimateParams(reduction=0.3),
        smooth=SmoothParams(iterations=5, angle_deg=1.0),
    )
    again = ReconParams.from_dict(json.loads(json.dumps(p.to_dict())))
    assert again == p
    assert ReconParams.from_dict({}) == ReconParams()


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"decimate": {"reduction": 0}}, "reduction"),
        ({"decimate": {"reduction": 1.5}}, "reduction"),
        ({"smooth": {"iterations": 0}}, "iterations"),
        ({"smooth": {"angle_deg": -1}}, "angle"),
        ({"iso": {"preset": "femur"}}, "preset"),
        ({"iso": {"iso": 1, "preset": "bone"}}, "not both"),
        ({"colour": {}}, "Unknown parameter groups"),
        ({"smooth": {"iters": 2}}, "Unknown smooth parameters"),
    ],
)
def test_params_reject_bad_values(data, match):
    with pytest.raises(ValueError, match=match):
        ReconParams.from_dict(data)


# ------------------------------------------------------------------------------------------- gaussian
@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_gaussian_matches_scipy(device, dtype):
    from engine.device import resolve_backend
    from engine.params import GaussianParams
    from engine.volume.gaussian import smooth_volume

    be = resolve_backend(device)
    vol = np.random.default_rng(1).integers(0, 3000, size=(9, 10, 11)).astype(dtype)
    got = be.to_host(smooth_volume(be.from_host(vol), GaussianParams(0.5)))
    ref = ndimage.gaussian_filter(vol.astype(np.float64), sigma=0.5, truncate=2.0, mode="nearest")
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-2)


# ------------------------------------------------------------------------------------------- smoothing
def test_smoothing_keeps_volume_watertightness_and_orientation(wp_device):
    from engine.surface.smooth import smooth_mesh

    verts, faces = ball_mesh(noise=0.05)
    before = signed_volume(verts, faces)
    for iterations in (1, 10):
        smoothed, info = smooth_mesh(verts, faces, SmoothParams(iterations=iterations, angle_deg=0.5), wp_device)
        assert smoothed.shape == verts.shape
        assert_closed_manifold(smoothed, faces)
        assert abs(signed_volume(smoothed, faces) / before - 1) < 0.005
        assert sum(info["moved_per_iteration"]) > 0


def test_smoothing_respects_the_angle(wp_device):
    """No face normal turns by the threshold or more in one iteration; a larger angle moves more vertices."""
    from engine.surface.smooth import smooth_mesh

    verts, faces = ball_mesh(noise=0.05)

    def normals(v):
        a, b, c = (v[faces[:, k]][:, ::-1].astype(np.float64) for k in range(3))
        n = np.cross(b - a, c - a)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    small, _ = smooth_mesh(verts, faces, SmoothParams(iterations=1, angle_deg=2.0), wp_device)
    turn = np.degrees(np.arccos(np.clip(np.sum(normals(verts) * normals(small), axis=1), -1, 1)))
    assert turn.max() < 2.0 + 1e-3
    large, _ = smooth_mesh(verts, faces, SmoothParams(iterations=1, angle_deg=20.0), wp_device)
    moved_small = np.count_nonzero(np.any(small != verts, axis=1))
    moved_large = np.count_nonzero(np.any(large != verts, axis=1))
    assert moved_large > moved_small > 0


def test_smoothing_keeps_open_boundaries(wp_device):
    from engine.surface.smooth import smooth_mesh, unique_edges

    z, y, x = np.indices((12, 14, 16), dtype=np.float32)
    vol = 6.3 - x + 0.3 * np.sin(y) + 0.2 * np.cos(z)
    verts, faces = marching_cubes_33(vol, 0.0, device="cpu")
    edges, boundary = unique_edges(faces)
    fixed = np.unique(edges[boundary])
    smoothed, _ = smooth_mesh(verts, faces, SmoothParams(iterations=5, angle_deg=10.0), wp_device)
    np.testing.assert_array_equal(smoothed[fixed], verts[fixed])
    assert topology(smoothed, faces) == topology(verts, faces)


def test_vertex_normals_point_outward(wp_device):
    from engine.surface.normals import vertex_normals

    verts, faces = ball_mesh()
    n = vertex_normals(verts, faces, wp_device)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-5)
    centre = verts.mean(axis=0)
    assert (np.sum(n * (verts - centre), axis=1) > 0).all()


# ------------------------------------------------------------------------------------------- iso level and crop
def test_choose_level():
    hu = Volume(np.zeros((4, 4, 4), np.int16), (1.0, 1.0, 1.0), units="HU")
    raw = Volume(np.r_[np.zeros(32), np.full(32, 200)].reshape(4, 4, 4).astype(np.uint8), (1.0, 1.0, 1.0))
    assert choose_level(hu, ReconParams())[0] == 300.0
    assert choose_level(hu, ReconParams(iso=IsoParams(preset="compact-bone")))[0] == 662.0
    assert choose_level(raw, ReconParams(iso=IsoParams(iso=42.0))) == (42.0, "given")
    assert choose_level(raw, ReconParams(iso=IsoParams(preset="bone", hu_offset=1024)))[0] == 1324.0
    level, how = choose_level(raw, ReconParams())
    assert how.startswith("Otsu") and level == 100.0  # midway between the classes 0 and 200
    with pytest.raises(InputError, match="not calibrated in HU"):
        choose_level(raw, ReconParams(iso=IsoParams(preset="bone")))


def test_crop_and_threshold():
    data = np.arange(10 * 8 * 6, dtype=np.int16).reshape(10, 8, 6)
    vol = Volume(data, (2.0, 1.0, 0.5), origin_mm=(0.0, 0.0, 0.0))
    cropped = crop_volume(vol, ((2.0, 8.0), (1.0, 3.0), (0.0, 1.0)))
    np.testing.assert_array_equal(cropped.data, data[1:5, 1:4, 0:3])
    assert cropped.origin_mm == (0.0, 1.0, 2.0)  # (x, y, z) of the first kept sample
    with pytest.raises(InputError, match="fewer than 2"):
        crop_volume(vol, ((0.0, 1.0), (0.0, 7.0), (0.0, 2.0)))
    thr = preprocess_volume(vol, PreprocessParams(threshold=200.0))
    assert (
        thr.data.min() == 0 and (thr.data[data < 200] == 0).all() and (thr.data[data >= 200] == data[data >= 200]).all()
    )
