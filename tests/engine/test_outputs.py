"""engine.outputs: the files laid out on the device match the host exporters (the slow obvious reference)."""

from __future__ import annotations

import numpy as np
import pytest

from engine.export.glb import read_glb, to_glb
from engine.export.printcheck import zero_area_faces
from engine.export.stl import to_stl
from engine.isosurface import marching_cubes_33
from engine.orient import Frame, export_meshes
from engine.outputs import STL_HEADER, lay_out, write_outputs
from engine.pipeline import Reconstruction
from engine.stages.normals import vertex_normals
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


@pytest.mark.parametrize("mirrored", [False, True])
def test_files_match_the_host_exporters(blob, tmp_path, mirrored):
    frame = _oblique_frame(mirrored)
    recon = Reconstruction(blob, {"frame": frame.to_dict()})
    paths = write_outputs(recon, tmp_path, device="cpu")
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
    from engine.pipeline import reconstruct
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


def test_zero_area_faces_are_counted_on_the_device(blob):
    import warp as wp

    v = blob.vertices.copy()
    f = np.vstack([blob.faces, [[0, 1, 1]], [[2, 3, 4]]]).astype(np.int32)
    v[4] = v[2] + 2 * (v[3] - v[2])  # (2, 3, 4) collinear: exactly zero area? not always in float32
    with wp.ScopedDevice("cpu"):
        lay = lay_out(
            wp.array(v, dtype=wp.vec3),
            wp.array(f, dtype=wp.vec3i),
            wp.array(blob.normals, dtype=wp.vec3),
            Frame.from_dict(None),
        )
    assert lay.zero_area == zero_area_faces(v, f) >= 1
