"""The viewer files: meshopt GLB (decoded with the library's own decoder), USDZ (read back with USD), and the
numpy thumbnail (checked against what an orthographic view of known shapes must show)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from engine.export.glb import read_glb, to_glb
from engine.export.meshopt import EXT, QUANT, read_meshopt_glb, to_meshopt_glb
from engine.export.preview import render, to_preview_png
from engine.export.usdz import to_usdz


def _engine_mesh(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """trimesh (x, y, z) mm -> the engine's (z, y, x) vertices and faces."""
    return mesh.vertices[:, ::-1].astype(np.float32), mesh.faces.astype(np.int32)


def _canonical(tris: np.ndarray) -> set[tuple[int, ...]]:
    """Triangles as a set, each rotated to start at its smallest index (orientation kept)."""
    first = tris.argmin(axis=1)
    rolled = np.stack([tris[np.arange(len(tris)), (first + k) % 3] for k in range(3)], axis=1)
    return set(map(tuple, rolled.tolist()))


@pytest.fixture(scope="module")
def ball_on_rod() -> trimesh.Trimesh:
    """A 40 mm ball with an 80 mm rod above it along scanner +z (superior: glTF +Y, the image's top)."""
    ball = trimesh.creation.icosphere(4, radius=40.0)
    rod = trimesh.creation.box(extents=[20, 20, 80])
    rod.apply_translation([0, 0, 80])
    return trimesh.util.concatenate([ball, rod])


@pytest.mark.parametrize("subdivisions", [1, 6])  # uint16 and uint32 indices
def test_meshopt_glb_decodes_to_the_plain_glb(subdivisions: int) -> None:
    verts, faces = _engine_mesh(trimesh.creation.icosphere(subdivisions, radius=30.0))
    data = to_meshopt_glb(verts, faces)
    doc = json.loads(data[20 : 20 + int.from_bytes(data[12:16], "little")])
    assert set(doc["extensionsRequired"]) == {EXT, QUANT}
    positions, normals, tris = read_meshopt_glb(data)
    ref_pos, _, ref_tris = read_glb(to_glb(verts, faces))
    assert len(tris) == len(faces) and len(positions) == len(verts)
    # the same triangles, vertices renumbered and corners rotated: map each vertex to the reference's nearest
    quantum = np.ptp(ref_pos, axis=0).max() / 65535
    dist, nearest = cKDTree(ref_pos).query(positions)
    assert dist.max() < 2 * quantum
    assert len(np.unique(nearest)) == len(ref_pos)
    assert _canonical(nearest[tris]) == _canonical(ref_tris.astype(np.int64))
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=0.02)
    decoded = trimesh.Trimesh(positions, tris, process=False)
    assert decoded.is_watertight and decoded.volume > 0  # winding kept: outward
    np.testing.assert_allclose(decoded.volume, trimesh.Trimesh(ref_pos, ref_tris).volume, rtol=1e-3)
    if len(faces) > 10_000:  # past the JSON's share, the codec and the quantization save more than half
        assert len(data) < len(to_glb(verts, faces)) / 2


def test_usdz_holds_the_mesh_in_metres_y_up(tmp_path, ball_on_rod: trimesh.Trimesh) -> None:
    from pxr import Usd, UsdGeom, UsdShade

    verts, faces = _engine_mesh(ball_on_rod)
    data = to_usdz(verts, faces)
    assert data[:2] == b"PK"  # a zip package
    path = tmp_path / "m.usdz"
    path.write_bytes(data)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    (prim,) = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    mesh = UsdGeom.Mesh(prim)
    points = np.asarray(mesh.GetPointsAttr().Get())
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3] * len(faces)
    ref_pos, _, _ = read_glb(to_glb(verts, faces))
    np.testing.assert_allclose(points, ref_pos, atol=1e-7)  # the glTF files' frame: the rod is up (+Y)
    assert points[:, 1].max() > 0.1 and points[:, 1].min() > -0.05
    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    assert material, "the mesh has no material bound"


def test_thumbnail_is_upright_and_framed(ball_on_rod: trimesh.Trimesh) -> None:
    import imageio.v3 as iio

    verts, faces = _engine_mesh(ball_on_rod)
    image = iio.imread(io.BytesIO(to_preview_png(verts, faces, size=200)))
    assert image.shape == (200, 200, 4) and image.dtype == np.uint8
    seen = image[..., 3] > 0
    rows, cols = np.nonzero(seen)
    assert rows.min() > 3 and rows.max() < 196 and cols.min() > 3 and cols.max() < 196  # inside the margin
    assert rows.max() - rows.min() > 0.8 * 200  # fills the height: the model is 160 mm tall, 80 mm wide
    width = seen.sum(axis=1)
    top, bottom = width[rows.min() : rows.min() + 40].mean(), width[rows.max() - 80 : rows.max() - 40].mean()
    assert top < 0.6 * bottom, "the narrow rod must be at the top (superior up)"
    lit = image[..., :3][seen].mean(axis=1)
    assert lit.min() > 30 and lit.max() > 150  # shaded, never black


def test_thumbnail_z_buffer_keeps_the_nearer_surface() -> None:
    """Two squares one behind the other, the far one drawn last: the near one's shade must win."""
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=float)
    near, far = quad + np.array([0, 0, 1.0]), quad * np.array([2, 2, 1]) + np.array([0, 0, -1.0])
    positions = np.vstack([near, far])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    normals = np.vstack([np.tile([0, 0, 1.0], (4, 1)), np.tile([0.0, -0.6, 0.8], (4, 1))])  # far: shaded darker
    image = render(positions, faces, normals, size=64, yaw_deg=0, pitch_deg=0, margin=0.0)
    centre, corner = image[32, 32, :3].astype(int), image[2, 2, :3].astype(int)
    assert image[32, 32, 3] == 255 and image[2, 2, 3] == 255
    assert centre.sum() != corner.sum(), "the near square must cover the far one in the centre"
    assert centre.sum() > corner.sum()  # the near one faces the light more


def test_thumbnail_ties_go_to_the_lower_triangle() -> None:
    """Two copies of a square at the same depth, shaded differently: the one listed first is seen, every run."""
    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=float)
    positions = np.vstack([quad, quad])
    bright, dark = np.tile([0.0, 0.0, 1.0], (4, 1)), np.tile([0.0, -0.6, 0.8], (4, 1))
    first = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    seen = []
    for normals in (np.vstack([bright, dark]), np.vstack([dark, bright])):
        image = render(positions, first, normals, size=32, yaw_deg=0, pitch_deg=0, margin=0.0)
        assert (image[..., 3] == 255).all()
        seen.append(image[16, 16, :3].astype(int).sum())
    assert seen[0] > seen[1], "the first-listed square must win the tie, whichever it is"
    again = render(positions, first, np.vstack([bright, dark]), size=32, yaw_deg=0, pitch_deg=0, margin=0.0)
    assert again[16, 16, :3].astype(int).sum() == seen[0]


@pytest.mark.parametrize("one_at_a_time", [False, True], ids=["beside", "one at a time"])
def test_small_files_encode_beside_each_other_with_warp_on_the_calling_thread(
    monkeypatch: pytest.MonkeyPatch, ball_on_rod: trimesh.Trimesh, tmp_path: Path, one_at_a_time: bool
) -> None:
    """``engine.job.outputs`` encodes the viewer files at once (under a host memory bound: one at a time, in one
    thread); an exporter that runs Warp kernels (the preview) stays on the calling thread (Warp copies from a second
    thread hung the H100 host once), the others run in threads; every file is written as its exporter alone makes
    it."""
    import threading

    from engine.export import viewers
    from engine.export.files import FILES, viewing_files
    from engine.job import outputs
    from engine.types import Mesh

    vertices, faces = _engine_mesh(ball_on_rod)
    mesh = Mesh(vertices, faces, None)
    threads: dict[str, str] = {}
    plain = viewers.small_files(mesh, mesh)

    def recorded(name: str, encode) -> object:
        def run() -> bytes:
            threads[name] = threading.current_thread().name
            return encode()

        return run

    real = viewers.small_files
    monkeypatch.setattr(viewers, "small_files", lambda *a: {n: recorded(n, e) for n, e in real(*a).items()})
    sizes, seconds = outputs._encode_small(mesh, mesh, {}, None, tmp_path, one_at_a_time)
    assert list(sizes) == list(seconds) == [f.name for f in viewing_files()]
    here = threading.current_thread().name
    for name in sizes:
        on_here = threads[name] == here
        assert on_here == FILES[name].device, (name, threads[name])
        data = (tmp_path / name).read_bytes()
        assert sizes[name] == len(data) and data == plain[name](), name
    assert FILES["preview.png"].device
    beside = {t for n, t in threads.items() if not FILES[n].device}
    assert len(beside) == 1 if one_at_a_time else len(beside) > 1, beside


def test_a_fresh_process_encodes_the_small_files_in_threads_without_hanging() -> None:
    """The first use of the exporters in a process loads USD's and meshoptimizer's native libraries; loaded from two
    threads at once they deadlocked (USD's initialisers wait for the GIL inside ``dlopen``). Looking an exporter up
    (``engine.export.files``, on the calling thread) loads them before any encoding thread starts."""
    import subprocess
    import sys

    code = (
        "import trimesh, numpy as np\n"
        "from engine.job.outputs import _encode_small\n"
        "from engine.types import Mesh\n"
        "m = trimesh.creation.icosphere(3, radius=20.0)\n"
        "mesh = Mesh(m.vertices[:, ::-1].astype(np.float32), m.faces.astype(np.int32), None)\n"
        "import tempfile, pathlib\n"
        "files, _ = _encode_small(mesh, mesh, {}, None, pathlib.Path(tempfile.mkdtemp()))\n"
        "print(sorted(files))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180, check=True)
    assert "model.usdz" in done.stdout and "phone_meshopt.glb" in done.stdout
