"""Geometry against scikit-image's Lewiner MC33 (a speed and geometry reference, never a topology oracle)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from engine.io.stack import load_slice_zip
from engine.isosurface import marching_cubes_33
from tests.engine.scans import scan_file

SCANS = [
    ("headsq_ct", "headsq_png16.zip", 1150.5, (1.5, 3.2, 3.2)),
    ("cranium_ct", "cranium_ct_png16.zip", 1324.5, (1.5, 0.9570312, 0.9570312)),
    ("pelvis_ct", "pelvis_ct_png16.zip", 1324.5, (5.0, 1.663, 1.663)),
]


@pytest.mark.parametrize(("folder", "name", "level", "spacing"), SCANS)
def test_counts_and_vertices_agree_with_lewiner(device, folder, name, level, spacing):
    skimage = pytest.importorskip("skimage.measure")
    vol = load_slice_zip(scan_file(folder, name))
    verts, faces = marching_cubes_33(vol, level, spacing=spacing, device=device)
    ref_v, ref_f, _, _ = skimage.marching_cubes(vol.astype(np.float32), level, spacing=spacing, method="lewiner")
    assert abs(len(verts) / len(ref_v) - 1) < 0.005
    assert abs(len(faces) / len(ref_f) - 1) < 0.005
    # vertices on grid edges (two coordinates on the grid) are the same interpolated points
    grid = np.asarray(verts, np.float64) / np.asarray(spacing)
    on_grid = np.abs(grid - np.round(grid)) < 1e-4
    edge_pts = on_grid.sum(axis=1) >= 2
    assert edge_pts.mean() > 0.99
    dist, _ = cKDTree(ref_v).query(verts[edge_pts])
    assert np.quantile(dist, 0.999) < 1e-3 * max(spacing)
    # every vertex, interior ones included, is near the reference surface (within one voxel diagonal)
    dist_all, _ = cKDTree(ref_v).query(verts)
    assert dist_all.max() < np.linalg.norm(spacing)
