"""Topology of the trilinear interpolant: refinement invariance, published counter-examples, CT truth, ties."""

from __future__ import annotations

import json

import numpy as np
import pytest

from engine.io.stack import load_slice_zip
from engine.isosurface import IsosurfaceStats, marching_cubes_33
from tests.conftest import shared_file
from tests.engine.meshutil import assert_closed_manifold, assert_valid_mesh, refine_trilinear, topology
from tests.engine.scans import scan_file

# (folder, zip, level, components, Euler characteristic): closed surfaces, trilinear truth from the issue
CT_TRUTH = [
    ("headsq_ct", "headsq_png16.zip", 1150.5, 74, -44),
    ("cranium_ct", "cranium_ct_png16.zip", 1324.5, 210, -54),
    ("pelvis_ct", "pelvis_ct_png16.zip", 1324.5, 449, -122),
]


def load_scan(folder: str, name: str) -> np.ndarray:
    return load_slice_zip(scan_file(folder, name))


def topo_of(volume: np.ndarray, level: float, device: str, closed: bool) -> tuple[int, int]:
    stats = IsosurfaceStats()
    verts, faces = marching_cubes_33(volume, level, device=device, closed=closed, stats=stats)
    assert stats.table_misses == 0
    assert_valid_mesh(verts, faces)
    t = topology(verts, faces)
    assert t.nonmanifold_edges == 0 and t.inconsistent_edges == 0 and t.duplicate_faces == 0
    if closed:
        assert t.boundary_edges == 0
    return t.components, t.euler


# ------------------------------------------------------------------------------------------- refinement
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("closed", [False, True])
def test_refinement_invariance_on_noise(device, seed, closed):
    """Refining by trilinear interpolation keeps the interpolant, so components and Euler must not change."""
    rng = np.random.default_rng(seed)
    vol = rng.integers(0, 100, size=(7, 8, 9)).astype(np.float64)
    results = {k: topo_of(refine_trilinear(vol, k).astype(np.float32), 49.5, device, closed) for k in (1, 3, 5)}
    assert len(set(results.values())) == 1, results


def test_refinement_invariance_on_smooth_noise_with_many_tunnels(device):
    """Low-amplitude noise around the level: dense ambiguous faces and interior saddles."""
    rng = np.random.default_rng(11)
    vol = rng.normal(size=(6, 6, 6))
    vol = np.sign(vol) * np.abs(vol) ** 0.3  # push values toward the level: more ambiguity
    results = {k: topo_of(refine_trilinear(vol, k).astype(np.float32), 0.0, device, False) for k in (1, 3, 5)}
    assert len(set(results.values())) == 1, results


@pytest.mark.slow
@pytest.mark.parametrize(("folder", "name", "level", "components", "euler"), CT_TRUTH)
def test_refinement_invariance_on_scans(device, folder, name, level, components, euler):
    vol = load_scan(folder, name)
    for k in (1, 3, 5):  # k = 5 turns the skull into ~0.9 G voxels: meant for a GPU machine
        refined = refine_trilinear(vol, k).astype(np.float32)
        assert topo_of(refined, level, device, True) == (components, euler), k
        del refined


def test_refinement_invariance_on_scan_crop(device):
    """Always-fast version: a crop of the skull refined by 3 and 5."""
    vol = load_scan("cranium_ct", "cranium_ct_png16.zip")[40:52, 60:110, 40:90].astype(np.float64)
    results = {k: topo_of(refine_trilinear(vol, k).astype(np.float32), 1324.5, device, False) for k in (1, 3, 5)}
    assert len(set(results.values())) == 1, results


# ------------------------------------------------------------------------------------------- known answers
def test_custodio_counter_examples(device):
    cases = json.loads(shared_file("mc33_cases", "cases.json").read_text())
    for name, case in cases.items():
        vol = np.load(shared_file("mc33_cases", f"{name}.npy"))
        expected = (case["open_surface_components"], case["open_surface_euler"])
        assert topo_of(vol, case["level"], device, False) == expected, name


@pytest.mark.parametrize(("folder", "name", "level", "components", "euler"), CT_TRUTH)
def test_ct_scans_match_trilinear_truth(device, folder, name, level, components, euler):
    vol = load_scan(folder, name)
    assert topo_of(vol, level, device, True) == (components, euler)


# ------------------------------------------------------------------------------------------- ties
@pytest.mark.parametrize("level", [1150, 1000, 500])
def test_integer_levels_on_integer_data(device, level):
    """Samples equal to the level count as above it: still watertight, 2-manifold, no zero-area faces."""
    vol = load_scan("headsq_ct", "headsq_png16.zip")
    ties = int(np.count_nonzero(vol == level))
    assert ties > 0
    verts, faces = marching_cubes_33(vol, level, device=device, closed=True)
    assert_closed_manifold(verts, faces)
    v = verts.astype(np.float64)
    area2 = np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)
    assert area2.min() > 0
    # the tie rule equals lowering the level by an infinitesimal amount (1e-6 against integer steps)
    shifted = vol.astype(np.float32) - np.float32(level)
    below = marching_cubes_33(shifted, -1e-6, device=device, closed=True)
    assert topology(verts, faces) == topology(*below)


def test_ties_everywhere_synthetic(device):
    rng = np.random.default_rng(5)
    vol = rng.integers(0, 3, size=(12, 13, 14)).astype(np.int16)  # a third of the samples equal the level
    verts, faces = marching_cubes_33(vol, 1, device=device, closed=True)
    assert_closed_manifold(verts, faces)
    assert len(np.unique(np.round(verts, 6), axis=0)) == len(verts)  # no coincident vertices
