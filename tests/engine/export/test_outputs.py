"""engine.job.outputs: the files laid out on the device match the host exporters (the slow obvious reference)."""

from __future__ import annotations

import numpy as np
import pytest

from engine.export.glb import read_glb, to_glb
from engine.export.printcheck import zero_area_faces
from engine.export.stl import to_stl
from engine.isosurface import marching_cubes_33
from engine.orient import Frame, export_meshes
from engine.job.outputs import STL_HEADER, lay_out, write_outputs
from engine.job.pipeline import Reconstruction
from engine.surface.normals import vertex_normals
from engine.types import Mesh


def _stl_floats(data: bytes) -> np.ndarray:
    n = int.from_bytes(data[80:84], "little")
    rec = np.frombuffer(data, np.uint8, 50 * n, 84).reshape(n, 50)
    assert not rec[:, 48:].any()  # attribute bytes
    return np.ascontiguousarray(rec[:, :48]).view("<f4").reshape(n, 12)


def _oblique_frame(mirrored: bool) -> Frame:
    """A DICOM-like map: rotated about an oblique axis, offset, and mirrored when asked."""
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + np.sin(0.7) * k + (1 - np.cos(0.7)) * k @ k
    if mirrored:
        rot = rot @ np.diag([1.0, 1.0, -1.0])
    return Frame(rot, np.array([-120.5, 33.25, 910.0]), "test")


@pytest.fixture(scope="module")
def blob() -> Mesh:
    z, y, x = np.mgrid[:24, :26, :28].astype(np.float32)
    field = np.sqrt((z - 11) ** 2 + ((y - 12) / 1.2) ** 2 + ((x - 13) / 1.4) ** 2)
    field = np.minimum(field, np.sqrt((z - 6) ** 2 + (y - 20) ** 2 + (x - 6) ** 2) + 3)
    v, f = marching_cubes_33(field, 7.5, spacing=(1.5, 0.8, 0.6), device="cpu", closed=True)
    return Mesh(v, f, vertex_normals(v, f, "cpu"))


@pytest.mark.parametrize("mirrored, chunk", [(False, None), (True, None), (True, 97)])
def test_files_match_the_host_exporters(blob, tmp_path, mirrored, chunk):
    """The laid-out files equal the host exporters' (also with the STL's facets laid out a few faces at a time)."""
    from engine.budget import Budget, Costs

    budget = Budget() if chunk is None else Budget(costs=Costs(layout_chunk_faces=chunk))  # no limit, other chunks
    frame = _oblique_frame(mirrored)
    recon = Reconstruction(blob, {"frame": frame.to_dict()})
    paths = write_outputs(recon, tmp_path, device="cpu", max_device_bytes=budget)
    patient, view, info = export_meshes(blob, frame.to_dict())
    assert recon.report["frame"]["gltf_centre_lps_mm"] == info["gltf_centre_lps_mm"]
    want = _stl_floats(to_stl(patient.vertices, patient.faces, header=STL_HEADER))
    got_bytes = paths["model.stl"].read_bytes()
    assert (
        got_bytes[:84]
        == to_stl(patient.vertices[:0], patient.faces[:0], header=STL_HEADER)[:80]
        + np.uint32(len(blob.faces)).tobytes()
    )
    np.testing.assert_allclose(_stl_floats(got_bytes), want, rtol=0, atol=2e-4)  # mm, rounding of the map only
    p0, n0, t0 = read_glb(to_glb(view.vertices, view.faces, view.normals))
    p1, n1, t1 = read_glb(paths["model.glb"].read_bytes())
    np.testing.assert_array_equal(t1, t0)
    np.testing.assert_allclose(p1, p0, atol=2e-7)  # metres
    np.testing.assert_allclose(n1, n0, atol=1e-5)
    assert recon.report["print_check"]["passed"]


def test_device_and_host_meshes_give_the_same_files(tmp_path):
    from engine.params import ReconParams
    from engine.job.pipeline import reconstruct
    from engine.types import Volume

    z, y, x = np.mgrid[:20, :22, :24].astype(np.float32)
    vol = Volume((200.0 - 20 * np.sqrt((z - 9) ** 2 + (y - 10) ** 2 + (x - 11) ** 2)).astype(np.float32), (1, 1, 1))
    params = ReconParams.from_dict({"iso": {"iso": 50.0}})
    recon = reconstruct(vol, params, device="cpu")
    assert recon.device_mesh is not None
    on_device = write_outputs(recon, tmp_path / "device", params, device="cpu")
    host = Reconstruction(recon.mesh, {k: v for k, v in recon.report.items() if k != "print_check"})
    on_host = write_outputs(host, tmp_path / "host", params, device="cpu")
    for name in ("model.stl", "model.glb", "ar.glb"):
        assert on_device[name].read_bytes() == on_host[name].read_bytes(), name


@pytest.mark.parametrize("chunk", [None, 97])
def test_zero_area_faces_are_counted_on_the_device(blob, chunk):
    import warp as wp

    from engine.budget import LAYOUT_CHUNK_FACES

    v = blob.vertices.copy()
    f = np.vstack([blob.faces, [[0, 1, 1]], [[2, 3, 4]]]).astype(np.int32)
    v[4] = v[2] + 2 * (v[3] - v[2])  # (2, 3, 4) collinear: exactly zero area? not always in float32
    with wp.ScopedDevice("cpu"):
        lay = lay_out(
            wp.array(v, dtype=wp.vec3),
            wp.array(f, dtype=wp.vec3i),
            wp.array(blob.normals, dtype=wp.vec3),
            Frame.from_dict(None),
            chunk_faces=LAYOUT_CHUNK_FACES if chunk is None else chunk,
        )
    assert lay.zero_area == zero_area_faces(v, f) >= 1


@pytest.fixture(scope="module")
def plate() -> tuple[np.ndarray, np.ndarray]:
    """A perforated plate: one closed piece with 18 x 18 tunnels (a topology-preserving copy keeps at least
    4 + 4 * 324 = 1300 faces)."""
    z, y, x = np.indices((16, 100, 100), dtype=np.float32)
    slab = np.minimum(3.5 - np.abs(z - 7.5), 46 - np.maximum(np.abs(y - 49.5), np.abs(x - 49.5)))
    holes = 1.6 - np.hypot((y - 49.5) % 5 - 2.5, (x - 49.5) % 5 - 2.5)
    holes[:, np.abs(np.arange(100) - 49.5) > 43, :] = -1
    holes[:, :, np.abs(np.arange(100) - 49.5) > 43] = -1
    return marching_cubes_33(np.minimum(slab, -holes), 0.0, spacing=(0.5, 0.5, 0.5), device="cpu", closed=True)


def _copies(
    v: np.ndarray, f: np.ndarray, budgets: list[int], closed: bool = True, room: int | None = None
) -> list[tuple]:
    import warp as wp

    from engine.decimation.viewing import viewing_copies
    from engine.surface.devmesh import mesh_stats_device

    with wp.ScopedDevice("cpu"):
        mesh = wp.array(v, dtype=wp.vec3), wp.array(f, dtype=wp.vec3i)
        copies = viewing_copies(*mesh, budgets, 1, closed, room)
        return [(p.numpy(), t.numpy(), info, mesh_stats_device(p, t)) for p, t, info in copies]


def test_ar_copy_of_a_clustered_phone_copy_is_clustered_from_the_same_mesh(plate):
    """The plate's largest (only) piece needs 1300 faces under the topology guard: a 1200-face phone copy is
    clustered without a decimation pass, and the AR copy is clustered from the same mesh (not decimated from the
    clustered copy): both within budget, reported as not topology-preserving, with valid faces."""
    from engine.surface.meshcheck import mesh_stats

    v, f = plate
    assert mesh_stats(v, f)["euler"] == 2 - 2 * 324
    (_, pf, phone, _), (av, af, ar, ar_stats) = _copies(v, f, [1200, 600])
    assert phone["topology_preserved"] is False and phone["passes"] == 0 and not phone["over_budget"]
    assert ar["topology_preserved"] is False and ar["passes"] == 0 and not ar["over_budget"]
    assert ar["clustered"]["input_faces"] == phone["clustered"]["input_faces"] == len(f)
    assert 0.6 * 1200 <= len(pf) <= 1200 and 0 < len(af) <= 600 and ar["faces"] == len(af)
    assert ar_stats["degenerate_faces"] == 0 and len(np.unique(np.sort(af, axis=1), axis=0)) == len(af)
    lo, hi = v.min(axis=0), v.max(axis=0)
    assert (av >= lo - 1e-4).all() and (av <= hi + 1e-4).all()


def test_a_mesh_too_large_to_cluster_in_the_room_is_decimated_to_what_fits_first(plate):
    """Clustering needs ``Costs.cluster`` bytes per face of its input: in half that room, the plate is first decimated
    (every guard kept) to what fits, then clustered within budget."""
    from engine.budget import Costs

    v, f = plate
    room = Costs().cluster * len(f) // 2
    ((_, pf, phone, _),) = _copies(v, f, [1200], room=room)
    tiled = phone["tiled_for_clustering"]
    # toward room // Costs.cluster (half the faces), within the tiles' tolerance
    assert tiled["faces_in"] == len(f) and tiled["faces"] <= 0.6 * len(f)
    assert phone["clustered"]["input_faces"] == tiled["faces"] and 0 < len(pf) <= 1200


def test_a_budget_above_the_topology_floor_is_decimated_first(plate):
    """At a budget the plate's genus allows in principle (>= 1300), the guarded decimation runs first (one round: a
    single piece has nothing to drop) and clustering only follows where it stalls above the budget; the AR copy
    then needs no decimation pass."""
    from engine.decimation.viewing import VIEW_MAX_PASSES

    v, f = plate
    (_, pf, phone, _), (_, af, ar, _) = _copies(v, f, [1500, 700])
    assert 0 < phone["passes"] <= VIEW_MAX_PASSES and len(pf) <= 1500 and len(af) <= 700
    if phone["topology_preserved"] is False:
        assert ar["passes"] == 0 and ar["clustered"]["input_faces"] == phone["clustered"]["input_faces"] < len(f)


def test_ar_copy_keeps_the_topology_where_the_budget_allows(blob):
    """A closed copy within reach of its budget stays watertight and 2-manifold, with the print model's pieces and
    Euler characteristic, in both copies (the AR copy continues from the phone copy, as a closed copy)."""
    from engine.surface.meshcheck import mesh_stats

    v, f = blob.vertices, blob.faces
    before = mesh_stats(v, f)
    copies = _copies(v, f, [len(f) // 2, len(f) // 4])
    for (_, cf, info, stats), budget in zip(copies, [len(f) // 2, len(f) // 4], strict=True):
        assert info["topology_preserved"] is True and info["passes"] > 0 and len(cf) <= budget
        assert stats["watertight"] and stats["manifold"]
        assert (stats["components"], stats["euler"]) == (before["components"], before["euler"])


def test_stalled_rounds():
    """Another round is worth it only while the last passes, kept up for a round, would close the gap."""
    from types import SimpleNamespace

    from engine.decimation.viewing import STALL_PASSES, VIEW_MAX_PASSES, _stalled

    guards = SimpleNamespace(passes=12, collapses=[500] * 12)
    assert _stalled(guards, 10)  # stopped before its pass limit: the guards refuse every edge
    busy = SimpleNamespace(passes=VIEW_MAX_PASSES, collapses=[50] * VIEW_MAX_PASSES)
    assert not _stalled(busy, 2 * 50 * VIEW_MAX_PASSES - 1)
    tail = SimpleNamespace(passes=VIEW_MAX_PASSES, collapses=[5000] * (VIEW_MAX_PASSES - STALL_PASSES) + [1] * 10)
    assert _stalled(tail, 2 * VIEW_MAX_PASSES + 1)
