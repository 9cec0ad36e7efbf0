"""Device mesh helpers: the device's mesh statistics and components agree with the host's (numpy) ones."""

from __future__ import annotations

import numpy as np
import pytest

from engine.isosurface import marching_cubes_33
from engine.surface.meshcheck import component_labels, mesh_stats


def _ball(r: float, centre: tuple[float, float, float], shape=(24, 24, 48)) -> np.ndarray:
    z, y, x = np.indices(shape, dtype=np.float32)
    return r - np.sqrt((z - centre[0]) ** 2 + (y - centre[1]) ** 2 + (x - centre[2]) ** 2)


def _meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    two = np.maximum(_ball(6, (11, 11, 11)), _ball(1.2, (11, 11, 35)))  # a ball and a speck
    v, f = marching_cubes_33(two, 0.0, spacing=(0.5, 0.7, 0.9), device="cpu", closed=True)
    _, y, x = np.indices((12, 14, 16), dtype=np.float32)
    ov, of = marching_cubes_33(6.3 - x + 0.3 * np.sin(y), 0.0, device="cpu")  # an open sheet
    keep = v[f].mean(axis=1)[:, 0] < 4.0
    bow_v = np.concatenate([v, v + 20.0]).astype(np.float32)  # two copies sharing one vertex: non-manifold
    bow_f = np.concatenate([f, f + len(v)])
    bow_f[bow_f == len(v)] = 0
    flipped = f.copy()
    flipped[: len(f) // 3] = flipped[: len(f) // 3, ::-1]  # inconsistent winding
    unused = np.concatenate([v, np.zeros((3, 3), np.float32)])
    return {
        "two pieces": (v, f),
        "open sheet": (ov, of),
        "cut ball": (v, f[keep]),
        "bow tie": (bow_v, bow_f),
        "flipped third": (v, flipped),
        "unused vertices": (unused, f),
    }


@pytest.mark.parametrize("name", list(_meshes()))
def test_mesh_stats_device_matches_host(name: str, device: str) -> None:
    import warp as wp

    from engine.surface.devmesh import mesh_stats_device

    v, f = _meshes()[name]
    host = mesh_stats(v, f)
    with wp.ScopedDevice(device):
        dev = mesh_stats_device(wp.array(v, dtype=wp.vec3), wp.array(f.astype(np.int32), dtype=wp.vec3i))
    floats = ("volume_mm3", "area_mm2")
    assert {k: dev[k] for k in host if k not in (*floats, "bbox_mm")} == {
        k: host[k] for k in host if k not in (*floats, "bbox_mm")
    }
    for k in floats:
        assert dev[k] == pytest.approx(host[k], rel=1e-9, abs=1e-9)
    np.testing.assert_allclose(dev["bbox_mm"]["min"], host["bbox_mm"]["min"])


def test_component_labels_device(device: str) -> None:
    import warp as wp

    from engine.surface.devmesh import component_labels_device

    v, f = _meshes()["bow tie"]
    n, host = component_labels(f, len(v))
    with wp.ScopedDevice(device):
        label = component_labels_device(wp.array(f.astype(np.int32), dtype=wp.vec3i), len(v)).numpy()
    # the same partition: labels map one to one
    pairs = set(zip(host.tolist(), label.tolist(), strict=True))
    assert len(pairs) == n == len(np.unique(label))


@pytest.mark.parametrize(("min_volume", "keep"), [(1.0, None), (None, 1), (0.0, 2), (1e9, None)])
def test_remove_islands_device_matches_host(min_volume, keep, device: str) -> None:
    import warp as wp

    from engine.surface.islands import remove_islands, remove_islands_device

    field = np.maximum.reduce([_ball(6, (11, 11, 11)), _ball(1.2, (11, 11, 35)), _ball(2.5, (5, 18, 40))])
    v, f = marching_cubes_33(field, 0.0, spacing=(0.5, 0.7, 0.9), device="cpu", closed=True)
    hv, hf, hinfo = remove_islands(v, f, min_volume_mm3=min_volume, keep_largest=keep)
    with wp.ScopedDevice(device):
        p, t, dinfo = remove_islands_device(
            wp.array(v, dtype=wp.vec3), wp.array(f, dtype=wp.vec3i), min_volume_mm3=min_volume, keep_largest=keep
        )
        dv, df = p.numpy(), t.numpy()
    assert {k: dinfo[k] for k in dinfo if "mm3" not in k} == {k: hinfo[k] for k in hinfo if "mm3" not in k}
    for k in ("removed_volume_mm3", "kept_volume_mm3", "largest_removed_mm3"):
        assert dinfo[k] == pytest.approx(hinfo[k], rel=1e-9, abs=1e-12)
    np.testing.assert_array_equal(dv, hv)  # same kept faces and vertices, in the same order
    np.testing.assert_array_equal(df, hf)
