"""engine.paper.metrics on known answers: identical shapes, concentric spheres, shifted slices, boxes on the grid."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from engine.isosurface import marching_cubes_33
from engine.paper.metrics import (
    even_slices,
    mesh_quality,
    min_angles_deg,
    rasterize_slices,
    sample_surface,
    slice_similarity,
    surface_distance,
    volume_area,
)

SPACING = (1.0, 0.8, 0.7)


def _zyx(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """A trimesh (x, y, z, outward) as an engine mesh: (z, y, x) vertices, the same faces stay outward."""
    return np.ascontiguousarray(mesh.vertices[:, ::-1], dtype=np.float32), mesh.faces.astype(np.int32)


@pytest.fixture(scope="module")
def blob() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer-valued volume of two overlapping balls, and its closed MC33 surface at a level that samples hit."""
    shape = (30, 36, 40)
    z, y, x = np.meshgrid(*(np.arange(n) * s for n, s in zip(shape, SPACING, strict=True)), indexing="ij")
    f = np.maximum(
        9.3 - np.sqrt((z - 13.2) ** 2 + (y - 13.9) ** 2 + (x - 12.1) ** 2),
        6.1 - np.sqrt((z - 17.0) ** 2 + (y - 16.3) ** 2 + (x - 19.6) ** 2),
    )
    volume = np.round(f * 40.0).astype(np.int16)  # ties: many samples equal the level exactly
    assert np.count_nonzero(volume == 0) > 20
    v, faces = marching_cubes_33(volume, 0.0, spacing=SPACING, device="cpu", closed=True)
    return volume, v.reshape(-1, 3), faces.reshape(-1, 3)


def test_identical_shapes_score_100_percent(blob):
    """The undecimated MC33 surface of the scan cuts every slice plane exactly along its threshold."""
    volume, v, f = blob
    sim = slice_similarity(v, f, volume, 0.0, SPACING)
    assert sim["slices"] == list(range(volume.shape[0]))
    assert sim["rmse_pct"] == 100.0
    assert sim["ssim_pct"] == pytest.approx(100.0, abs=1e-9)
    assert sim["dice"] == 1.0
    np.testing.assert_array_equal(rasterize_slices(v, f, volume.shape, SPACING), volume >= 0)


def test_identical_shapes_are_0_mm_apart(blob, device):
    _, v, f = blob
    d = surface_distance(v, f, v, f, n_points=20_000, device=device)
    # float32 queries; Warp skips near-degenerate slivers, whose neighbours lie within a micrometre
    assert d["mean_mm"] < 1e-5
    assert d["hausdorff_mm"] < 1e-3


def test_shifted_slices_lower_the_similarity(blob):
    volume, v, f = blob
    scores = []
    for shift_px in (1, 3):
        moved = v + np.array([0.0, 0.0, shift_px * SPACING[2]], np.float32)
        scores.append(slice_similarity(moved, f, volume, 0.0, SPACING))
    one, three = scores
    assert 0 < three["ssim_pct"] < one["ssim_pct"] < 100
    assert 0 < three["rmse_pct"] < one["rmse_pct"] < 100
    assert three["dice"] < one["dice"] < 1


def test_sphere_against_a_larger_sphere_gives_the_radius_difference(device):
    r, dr = 10.0, 0.5
    inner = _zyx(trimesh.creation.icosphere(subdivisions=5, radius=r))
    outer = _zyx(trimesh.creation.icosphere(subdivisions=5, radius=r + dr))
    d = surface_distance(inner[0], inner[1], outer[0], outer[1], n_points=50_000, device=device)
    # flat facets lie inside the true spheres by at most the sagitta over a facet's circumradius (<= edge / sqrt 3)
    edge = float(np.linalg.norm(np.diff(outer[0][outer[1][:, :2]], axis=1), axis=2).max())
    sagitta = (r + dr) - np.sqrt((r + dr) ** 2 - edge**2 / 3)
    for way in ("to_reference", "from_reference"):
        for key in ("mean_mm", "p95_mm", "max_mm"):
            assert abs(d[way][key] - dr) <= sagitta + 1e-4, (way, key, d[way][key])
    assert d["hausdorff_mm"] == pytest.approx(dr, abs=sagitta + 1e-4)


def _point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Slow obvious reference: distance from each point (N, 3) to each triangle (T, 3, 3) by projection and edges."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = p[:, None, :] - a[None]
    h = np.einsum("ntk,tk->nt", d, n)
    q = p[:, None, :] - h[..., None] * n[None]  # projection on the plane
    inside = np.ones(h.shape, bool)
    for u, w in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ntk,tk->nt", np.cross(w - u, q - u[None]), n) >= 0
    best = np.where(inside, np.abs(h), np.inf)
    for u, w in ((a, b), (b, c), (c, a)):
        e = w - u
        t = np.clip(np.einsum("ntk,tk->nt", p[:, None, :] - u[None], e) / np.einsum("tk,tk->t", e, e), 0, 1)
        best = np.minimum(best, np.linalg.norm(p[:, None, :] - (u[None] + t[..., None] * e[None]), axis=2))
    return best.min(axis=1)


def test_warp_query_matches_a_brute_force_reference(device):
    from engine.paper.metrics import SurfaceQuery

    mesh = trimesh.creation.icosphere(subdivisions=2, radius=3.0)
    mesh.vertices[:, 0] *= 1.7  # an ellipsoid, so that distances vary
    v, f = _zyx(mesh)
    pts = np.random.default_rng(1).uniform(-7, 7, (400, 3)).astype(np.float32)
    got = SurfaceQuery(v, f, device).distances(pts)
    want = _point_triangle_distance(pts.astype(np.float64), v[f].astype(np.float64))
    np.testing.assert_allclose(got, want, atol=2e-5)


def test_box_on_the_grid_is_half_open():
    """Faces, edges and corners exactly on slice planes, pixel rows and columns: the box [lo, hi) in every axis."""
    lo, hi = np.array([2, 3, 1]), np.array([6, 8, 5])
    box = trimesh.creation.box(bounds=[lo[::-1], hi[::-1]])  # (x, y, z) bounds in voxels
    v, f = _zyx(box)
    shape = (9, 11, 8)
    mask = rasterize_slices(v * np.float32(SPACING), f, shape, SPACING)
    want = np.zeros(shape, bool)
    want[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = True
    np.testing.assert_array_equal(mask, want)
    # the winding rule does not depend on the orientation
    np.testing.assert_array_equal(rasterize_slices(v * np.float32(SPACING), f[:, ::-1], shape, SPACING), want)


def test_rasterize_selected_slices_in_any_order(blob):
    volume, v, f = blob
    ks = [17, 3, 29, 0]
    np.testing.assert_array_equal(rasterize_slices(v, f, volume.shape, SPACING, ks), volume[ks] >= 0)


def test_even_slices_spread_and_keep_the_ends():
    np.testing.assert_array_equal(even_slices(10, None), np.arange(10))
    picked = even_slices(952, 64)
    assert len(picked) == 64 and picked[0] == 0 and picked[-1] == 951
    assert np.all(np.diff(picked) >= 14)
    with pytest.raises(ValueError, match="max_slices"):
        even_slices(10, 0)


def test_similarity_rejects_slices_below_the_ssim_window():
    v, f = _zyx(trimesh.creation.box(bounds=[[1, 1, 1], [3, 3, 3]]))
    with pytest.raises(ValueError, match="7x7"):
        slice_similarity(v, f, np.zeros((5, 5, 5), np.float32), 0.5, (1, 1, 1))


def test_samples_lie_on_the_surface_and_are_seeded():
    v, f = _zyx(trimesh.creation.icosphere(subdivisions=3, radius=2.0))
    a = sample_surface(v, f, 5000, seed=3)
    np.testing.assert_array_equal(a, sample_surface(v, f, 5000, seed=3))
    r = np.linalg.norm(a, axis=1)
    assert r.max() <= 2.0 + 1e-5 and r.min() > 1.98
    # area-uniform: the octants get the same share
    counts = np.bincount(((a > 0) * [4, 2, 1]).sum(axis=1), minlength=8)
    assert counts.min() > 0.8 * 5000 / 8


def test_min_angles_and_quality():
    v = np.array([[0, 0, 0], [0, 0, 1], [0, np.sqrt(3) / 2, 0.5], [0, 1, 0], [0, 0, 2]], np.float32)
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]], np.int32)
    np.testing.assert_allclose(min_angles_deg(v, f), [60.0, 45.0, 0.0], atol=1e-4)
    small = _zyx(trimesh.creation.icosphere(subdivisions=4, radius=5.0))
    big = (small[0] * np.float32(1.1), small[1])
    q = mesh_quality(*big, reference_stats=mesh_quality(*small))
    assert q["watertight"] and q["manifold"] and q["components"] == 1 and q["euler"] == 2
    assert q["volume_change_pct"] == pytest.approx(100 * (1.1**3 - 1), rel=1e-5)
    assert q["area_change_pct"] == pytest.approx(100 * (1.1**2 - 1), rel=1e-5)
    vol, area = volume_area(*small)
    assert vol == pytest.approx(4 / 3 * np.pi * 125, rel=0.01) and area == pytest.approx(4 * np.pi * 25, rel=0.01)
    assert 30 < q["min_angle_deg"]["p5"] <= q["min_angle_deg"]["p50"] <= 60
