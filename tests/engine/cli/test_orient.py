"""engine.orient: grid -> patient (LPS) for the STL, patient -> glTF (+Y superior, facing +Z, centred)."""

from __future__ import annotations

import io

import numpy as np
import pytest

from engine.export.glb import read_glb, zyx_to_gltf
from engine.isosurface import marching_cubes_33
from engine.orient import Frame, export_meshes, patient_frame, to_patient
from engine.params import IsoParams, OrientParams, ReconParams
from engine.types import Mesh, Volume
from tests.engine.meshutil import signed_volume

SPACING = (2.0, 1.0, 0.5)


def marked_volume() -> Volume:
    """A box with three bumps: on the first slice's side, on image row 0's side and on column 0's side."""
    vol = np.zeros((30, 32, 34), np.float32)
    vol[8:22, 8:24, 8:26] = 1.0
    vol[2:8, 14:18, 14:18] = 1.0  # toward slice 0
    vol[13:17, 2:8, 14:18] = 1.0  # toward row 0
    vol[13:17, 14:18, 2:8] = 1.0  # toward column 0
    return Volume(vol, SPACING)


@pytest.mark.parametrize(
    ("orient", "up", "front", "right_hand"),
    [
        (OrientParams(), "z", "y", "x"),  # default: slice 0 superior, row 0 anterior, column 0 patient's right
        (OrientParams(first_slice="inferior", flip_lr=True, flip_ap=True), None, None, None),
    ],
)
def test_stack_convention_puts_the_head_up_and_the_face_forward(orient, up, front, right_hand):
    vol = marked_volume()
    v, f = marching_cubes_33(vol.data, 0.5, spacing=SPACING, device="cpu", closed=True)
    grid = Mesh(v, f)
    frame = patient_frame(vol, orient)
    patient = to_patient(grid, frame)
    assert signed_volume(patient.vertices, patient.faces) > 0  # outward after the map, mirrored or not
    np.testing.assert_allclose(signed_volume(patient.vertices, patient.faces), signed_volume(v, f), rtol=1e-5)
    extent_xyz = (np.array(vol.data.shape) - 1)[::-1] * np.array(SPACING)[::-1]
    lps = patient.vertices[:, ::-1]
    assert (lps.min(axis=0) >= -1e-4).all() and (lps.max(axis=0) <= extent_xyz + 1e-4).all()  # the stack's box
    g = zyx_to_gltf(patient.vertices)  # glTF X, Y, Z
    idx = {axis: int(np.argmin(v[:, k])) for k, axis in enumerate("zyx")}
    if up is not None:
        assert g[idx["z"], 1] == pytest.approx(g[:, 1].max())  # slice 0 is the top (+Y)
        assert g[idx["y"], 2] == pytest.approx(g[:, 2].max())  # row 0 faces the viewer (+Z, anterior)
        assert g[idx["x"], 0] == pytest.approx(g[:, 0].min())  # column 0 is the patient's right (-X)
    else:  # every axis flipped: the same marks at the opposite ends
        assert g[idx["z"], 1] == pytest.approx(g[:, 1].min())
        assert g[idx["y"], 2] == pytest.approx(g[:, 2].min())
        assert g[idx["x"], 0] == pytest.approx(g[:, 0].max())


def test_dicom_geometry_places_the_mesh_in_lps():
    """A coronal-like series: direction and origin from the headers map grid points as origin + D @ (x, y, z)."""
    d = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # columns: grid x, y, z axes in LPS
    vol = Volume(
        np.zeros((4, 4, 4), np.float32), SPACING, origin_mm=(-10.0, 20.0, 30.0),
        direction=tuple(tuple(r) for r in d), units="HU", patient_frame=True,
    )  # fmt: skip
    frame = patient_frame(vol, OrientParams(first_slice="inferior", flip_lr=True))  # ignored for DICOM
    assert "DICOM" in frame.placed_by and not frame.mirrored
    pts_zyx = np.array([[0.0, 0.0, 0.0], [2.0, 1.0, 0.5], [6.0, 3.0, 1.5]], np.float32)
    mesh = to_patient(Mesh(pts_zyx, np.array([[0, 1, 2]], np.int32)), frame)
    expected = pts_zyx[:, ::-1] @ d.T + [-10.0, 20.0, 30.0]
    np.testing.assert_allclose(mesh.vertices[:, ::-1], expected, atol=1e-5)
    again = Frame.from_dict(frame.to_dict())
    np.testing.assert_allclose(again.matrix, frame.matrix)
    np.testing.assert_allclose(again.offset_mm, frame.offset_mm)


def test_export_meshes_centre_the_viewing_copy():
    v = np.array([[0, 0, 0], [0, 0, 10], [0, 20, 0], [30, 0, 0]], np.float32)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int32)
    frame = patient_frame(Volume(np.zeros((2, 2, 2), np.float32), (1.0, 1.0, 1.0)), OrientParams())
    print_mesh, view, info = export_meshes(Mesh(v, f), frame.to_dict())
    lo, hi = view.vertices.min(axis=0), view.vertices.max(axis=0)
    np.testing.assert_allclose(lo + hi, 0.0, atol=1e-6)
    np.testing.assert_allclose(print_mesh.vertices - view.vertices, np.tile(info["gltf_centre_lps_mm"][::-1], (4, 1)))
    assert info["stl"].startswith("LPS") and "centred" in info["gltf"]


def test_demo_head_is_upright_in_every_glb(tmp_path):
    """headsq: slice 0 is the top of the head; in model.glb the top of the skull is +Y and the model is centred."""
    from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
    from engine.io import load_volume
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct

    trimesh = pytest.importorskip("trimesh")
    vol = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    params = ReconParams(iso=IsoParams(iso=1150.0))
    recon = reconstruct(vol, params, device="cpu")
    paths = write_outputs(recon, tmp_path, params, device="cpu")
    pos, _, _ = read_glb(paths["model.glb"].read_bytes())
    np.testing.assert_allclose(pos.min(axis=0) + pos.max(axis=0), 0.0, atol=1e-4)  # centred (metres)
    grid = recon.mesh.vertices
    top, bottom = int(np.argmin(grid[:, 0])), int(np.argmax(grid[:, 0]))  # slice 0 side, last slice side
    assert pos[top, 1] == pytest.approx(pos[:, 1].max()) and pos[bottom, 1] == pytest.approx(pos[:, 1].min())
    # the face (low image rows) is toward +Z; the back of the skull toward -Z
    front = int(np.argmin(grid[:, 1]))
    assert pos[front, 2] == pytest.approx(pos[:, 2].max())
    stl = trimesh.load(paths["model.stl"])
    assert stl.is_watertight and stl.volume > 0
    ar = trimesh.load(io.BytesIO(paths["ar.glb"].read_bytes()), file_type="glb").to_geometry()
    assert ar.bounds[1][1] > 0.05 and ar.bounds[0][1] < -0.05  # centred too: the head spans both sides of Y = 0
    assert recon.report["frame"]["placed_by"].startswith("image stack convention: first slice superior")
