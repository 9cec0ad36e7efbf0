"""The defect template (issue 31, ``engine.defect``): the symmetry plane, synthetic one-sided defects cut from the
real skulls (Dice and rim gap against the removed bone), the refusals (an intact skull, a defect across the midline)
and ``bonemesh defect``'s files. The bundled headsq head always runs; the head phantom needs ../shared."""

from __future__ import annotations

import json

import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.errors import InputError, MidlineDefectError, NoDefectError
from engine.params import OrientParams
from engine.types import Volume
from tests.conftest import shared_file

HEADSQ_ORIENT = OrientParams(first_slice="superior")
HEADSQ_CRANIUM = (4, 18)  # the slices of the braincase (the scan starts at the orbits' roofs)


@pytest.fixture(scope="module")
def headsq() -> Volume:
    from engine.io import load_volume

    return load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)


def _cut(volume: Volume, direction, diameter, **kw):
    from engine.defect.synthetic import cut_defect

    return cut_defect(volume, HEADSQ_LEVEL, direction, diameter, slices=HEADSQ_CRANIUM, orient=HEADSQ_ORIENT, **kw)


def _run(volume: Volume, device: str, level: float = HEADSQ_LEVEL, orient=HEADSQ_ORIENT, **params):
    from engine.defect import DefectParams, run

    return run(volume, DefectParams(**params), level, device, orient=orient)


def test_the_plane_of_a_symmetric_phantom_is_found_within_a_small_angle():
    """An egg-shaped shell open at its base (one mirror plane), turned by a known rotation and moved off-centre."""
    from engine.defect import find_symmetry_plane

    shape, sp = (60, 80, 80), (2.0, 1.5, 1.5)
    a, b = np.radians(8.0), np.radians(4.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rot = rz @ ry
    centre = np.array([61.3, 58.7, 60.2])  # x, y, z mm: off the grid's middle
    z, y, x = np.indices(shape)
    p = np.stack([x * sp[2], y * sp[1], z * sp[0]], axis=-1) - centre
    q = p @ rot  # object frame (x: across the mirror plane)
    egg = 1.0 + 0.25 * q[..., 1] / 50  # wider at the back than in front
    r = np.sqrt((q[..., 0] / (40 * egg)) ** 2 + (q[..., 1] / 50) ** 2 + (q[..., 2] / 35) ** 2)
    solid = (r > 0.85) & (r < 1.0) & (q[..., 2] > -18)  # open at its base
    data = np.where(solid, 1000, 0).astype(np.uint16)
    plane = find_symmetry_plane(Volume(data, sp), 500.0)
    truth = rot[:, 0]  # the object's x axis in the grid
    angle = np.degrees(np.arccos(min(1.0, abs(float(np.dot(plane.normal_grid, truth))))))
    assert angle < 1.0, angle
    offset = float(np.dot(centre, truth)) * np.sign(np.dot(plane.normal_grid, truth))
    assert abs(plane.offset_grid_mm - offset) < 1.0
    assert plane.residual_mm < 1.5 and plane.inlier_fraction > 0.9


def test_a_synthetic_defect_gets_a_template_that_fills_it(headsq, device):
    from engine.defect.synthetic import dice

    cut = _cut(headsq, (1.0, -0.1, 0.0), 30.0)  # the patient's left temple, a 30 mm trephination
    res = _run(cut.volume, device)
    mask = res.full_mask()
    assert dice(mask, cut.removed) >= 0.7
    rim = res.rim()
    assert rim["gap_voxels"] <= 1.0
    assert res.side == "left"
    assert res.mesh_stats["watertight"] and res.mesh_stats["manifold"]
    assert res.volume_mm3 > 0.5 * cut.removed_mm3
    info = res.to_json()
    json.dumps(info, allow_nan=False)  # the file is plain JSON
    assert info["defect"]["side"] == "left" and info["plane"]["residual_mm"] > 0


def test_an_intact_skull_is_no_defect(headsq, device):
    with pytest.raises(NoDefectError, match="no one-sided defect"):
        _run(headsq, device)


def test_a_defect_across_the_midline_is_refused(headsq, device):
    from engine.defect import find_symmetry_plane

    plane = find_symmetry_plane(headsq, HEADSQ_LEVEL, orient=HEADSQ_ORIENT)
    cut = _cut(headsq, (0.0, -0.9, 0.3), 50.0, plane=plane, offset_mm=12.0)  # 50 mm wide, 12 mm off the midline
    with pytest.raises(MidlineDefectError, match="midline"):
        _run(cut.volume, device)


def test_a_defect_centred_on_the_midline_is_not_made_up(headsq, device):
    from engine.defect import find_symmetry_plane

    plane = find_symmetry_plane(headsq, HEADSQ_LEVEL, orient=HEADSQ_ORIENT)
    cut = _cut(headsq, (0.0, -0.9, 0.3), 40.0, plane=plane)
    with pytest.raises((NoDefectError, MidlineDefectError), match="midline"):
        _run(cut.volume, device)


def test_the_side_hint_keeps_that_side_only(headsq, device):
    cut = _cut(headsq, (1.0, -0.1, 0.0), 30.0)
    with pytest.raises(NoDefectError, match="right side"):
        _run(cut.volume, device, side="right")


def test_head_phantom_synthetic_defect(device):
    from engine.defect.synthetic import cut_defect, dice
    from engine.io import load_volume

    path = shared_file("head_phantom_dicom", "head_phantom_png16.zip")
    volume = load_volume(path, spacing_zyx_mm=(5.0, 0.451171875, 0.451171875))
    orient = OrientParams(first_slice="inferior")
    cut = cut_defect(volume, 1324.0, (-0.5, 0.85, 0.1), 30.0, slices=(12, 27), orient=orient)  # right occiput
    res = _run(cut.volume, device, level=1324.0, orient=orient)
    assert dice(res.full_mask(), cut.removed) >= 0.7
    assert res.rim()["gap_voxels"] <= 1.0
    assert res.side == "right"


def test_defect_params_check_and_round_trip():
    from engine.defect import DefectParams

    p = DefectParams(side="left", point_lps_mm=(1, 2, 3), min_volume_mm3=500.0)
    assert DefectParams.from_dict(json.loads(json.dumps(p.to_dict()))) == p
    for bad in ({"side": "up"}, {"point_lps_mm": (1, 2)}, {"max_faces": 3}, {"min_volume_mm3": -1.0}):
        with pytest.raises(ValueError):
            DefectParams(**bad)
    with pytest.raises(ValueError, match="unknown"):
        DefectParams.from_dict({"sides": "left"})


def test_cli_writes_a_watertight_implant_in_mm(tmp_path, headsq, capsys, device):
    from engine.cli import main
    from engine.export.stl import from_stl
    from engine.orient import patient_frame
    from engine.surface import mesh_stats

    cut = _cut(headsq, (-1.0, -0.1, 0.0), 30.0)  # the right temple
    scan = tmp_path / "cut.npy"
    np.save(scan, cut.volume.data)
    out = tmp_path / "out"
    args = ["defect", str(scan), "-o", str(out), "--voxel-size", "z=1.5,y=3.2,x=3.2", "--iso", str(HEADSQ_LEVEL),
            "--first-slice", "superior", "--device", device]  # fmt: skip
    assert main(args) == 0
    assert "implant.stl" in capsys.readouterr().out
    verts, faces = from_stl((out / "implant.stl").read_bytes())
    stats = mesh_stats(verts, faces)
    assert stats["watertight"] and stats["n_faces"] > 100
    # mm, in the patient frame of model.stl: inside the scan's box, and where the bone was removed
    frame = patient_frame(cut.volume, HEADSQ_ORIENT)
    idx = np.argwhere(cut.removed)[:, ::-1] * np.array(HEADSQ_SPACING_ZYX_MM[::-1])
    removed_lps = idx @ frame.matrix.T + frame.offset_mm
    xyz = verts[:, ::-1]
    assert np.all(xyz.min(axis=0) > removed_lps.min(axis=0) - 15)
    assert np.all(xyz.max(axis=0) < removed_lps.max(axis=0) + 15)
    info = json.loads((out / "defect.json").read_text())
    assert info["defect"]["side"] == "right"
    assert abs(info["defect"]["volume_mm3"] - stats["volume_mm3"]) < 1e-3 * stats["volume_mm3"] + 1
    assert info["implant"]["watertight"] is True


def test_cli_refuses_an_intact_skull_with_one_line(tmp_path, capsys):
    from engine.cli import main

    out = tmp_path / "demo"
    assert main(["defect", "--demo", "-o", str(out), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bonemesh: error: no one-sided defect")
    assert not (out / "implant.stl").exists()


def test_errors_are_input_errors():
    assert issubclass(NoDefectError, InputError) and issubclass(MidlineDefectError, InputError)


# --- the defect as a step of the reconstruction (ReconParams.defect): its files and the template's glTF node ---


def _glb_document(data: bytes) -> tuple[dict, bytes]:
    n = int.from_bytes(data[12:16], "little")
    return json.loads(data[20 : 20 + n]), data[20 + n + 8 :]


def _gltf_to_lps(positions_m: np.ndarray, centre_lps: np.ndarray) -> np.ndarray:
    from engine.export.glb import GLTF_FROM_XYZ

    return positions_m.astype(np.float64) / 1e-3 @ GLTF_FROM_XYZ + centre_lps


@pytest.fixture(scope="module")
def with_template(headsq, tmp_path_factory):
    """A 30 mm left-temple trephination, reconstructed with ``defect`` on, and its files."""
    from engine.defect.params import DefectParams
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct
    from engine.params import IsoParams, ReconParams

    cut = _cut(headsq, (1.0, -0.1, 0.0), 30.0)
    params = ReconParams(iso=IsoParams(iso=HEADSQ_LEVEL), orient=HEADSQ_ORIENT, defect=DefectParams())
    recon = reconstruct(cut.volume, params, device="cpu")
    out = tmp_path_factory.mktemp("with_template")
    return cut, recon, write_outputs(recon, out, params, device="cpu"), out


def test_reconstruct_with_defect_publishes_the_template_beside_the_model(with_template):
    from engine.export.files import engine_files
    from engine.export.glb import read_glb
    from engine.export.stl import from_stl
    from engine.surface import mesh_stats

    _cut, recon, paths, out = with_template
    assert set(paths) == set(engine_files(closed=True, defect=True))
    summary = recon.report["defect"]
    assert summary["found"] is True and summary["side"] == "left"
    info = json.loads((out / "defect.json").read_text())
    assert info["found"] is True and info["defect"]["side"] == "left"
    verts, faces = from_stl((out / "implant.stl").read_bytes())
    stats = mesh_stats(verts, faces)
    assert stats["watertight"] and stats["n_faces"] == summary["implant_faces"] == info["implant"]["faces"]
    report = json.loads((out / "report.json").read_text())
    assert report["defect"] == json.loads(json.dumps(summary)) and report["stage_seconds"]["defect"] > 0
    # model.glb: the bone, then the template as its own named node with its own (blue) material
    data = (out / "model.glb").read_bytes()
    doc, binary = _glb_document(data)
    assert [n["name"] for n in doc["nodes"]] == ["bone", "defect template"]
    assert doc["scenes"][0]["nodes"] == [0, 1]
    colours = [m["pbrMetallicRoughness"]["baseColorFactor"] for m in doc["materials"]]
    assert len(colours) == 2 and colours[0] != colours[1]
    assert all(v["byteOffset"] % 4 == 0 for v in doc["bufferViews"])
    prim = doc["meshes"][1]["primitives"][0]
    acc = doc["accessors"][prim["attributes"]["POSITION"]]
    view = doc["bufferViews"][acc["bufferView"]]
    pos = np.frombuffer(binary, np.float32, acc["count"] * 3, view["byteOffset"]).reshape(-1, 3)
    centre = np.array(report["frame"]["gltf_centre_lps_mm"])
    # the node is the implant.stl mesh, in the model's glTF frame: back in LPS mm it lies on the STL's vertices
    lps = _gltf_to_lps(pos, centre)
    assert np.allclose(np.sort(lps, axis=0), np.sort(verts[:, ::-1].astype(np.float64), axis=0), atol=1e-3)
    bone_pos = read_glb(data)[0]  # the bone itself is still the first mesh, unchanged for readers of one mesh
    assert len(bone_pos) == report["mesh"]["n_vertices"]


def test_the_phone_copies_carry_a_lighter_template_node(with_template):
    import DracoPy

    from engine.defect.step import view_faces
    from engine.export.glb import read_glb

    _, recon, _, out = with_template
    centre = np.array(recon.report["frame"]["gltf_centre_lps_mm"])
    implant_lps = recon.defect.result.mesh.vertices[:, ::-1].astype(np.float64)
    doc, binary = _glb_document((out / "phone.glb").read_bytes())  # Draco: one compressed primitive per node
    assert [n["name"] for n in doc["nodes"]] == ["bone", "defect template"]
    ext = doc["meshes"][1]["primitives"][0]["extensions"]["KHR_draco_mesh_compression"]
    view = doc["bufferViews"][ext["bufferView"]]
    mesh = DracoPy.decode(binary[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])
    assert 0 < len(mesh.faces) <= view_faces(recon.report["parameters"]["export"]["phone_max_triangles"])
    lps = _gltf_to_lps(np.asarray(mesh.points), centre)
    assert np.all(np.abs(lps.min(axis=0) - implant_lps.min(axis=0)) < 2.0)  # the same place, to Draco's steps
    assert np.all(np.abs(lps.max(axis=0) - implant_lps.max(axis=0)) < 2.0)
    ar = (out / "ar.glb").read_bytes()
    assert [n["name"] for n in _glb_document(ar)[0]["nodes"]] == ["bone", "defect template"]
    assert len(read_glb(ar)[2]) == recon.report["exports"]["ar.glb"]["faces"]  # the bone copy, as before


def test_reconstruct_without_a_defect_says_why_and_makes_no_implant(headsq, tmp_path):
    from engine.defect.params import DefectParams
    from engine.job.outputs import write_outputs
    from engine.job.pipeline import reconstruct
    from engine.params import IsoParams, ReconParams

    params = ReconParams(iso=IsoParams(iso=HEADSQ_LEVEL), orient=HEADSQ_ORIENT, defect=DefectParams())
    recon = reconstruct(headsq, params, device="cpu")
    paths = write_outputs(recon, tmp_path, params, device="cpu")
    assert "implant.stl" not in paths and not (tmp_path / "implant.stl").exists()
    info = json.loads(paths["defect.json"].read_text())
    assert info["found"] is False and info["code"] == "no_defect" and "no one-sided defect" in info["message"]
    assert recon.report["defect"]["found"] is False and paths["model.stl"].stat().st_size > 0
    doc, _ = _glb_document(paths["model.glb"].read_bytes())
    assert [n["name"] for n in doc["nodes"]] == ["bone"]


def test_a_model_with_a_template_is_not_reoriented(with_template):
    from engine.job.reorient import reorient
    from engine.params import OrientParams

    *_, out = with_template
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    with pytest.raises(InputError, match="defect template"):
        reorient(out, OrientParams(first_slice="inferior"), device="cpu")
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_recon_params_carry_the_defect_through_json():
    from engine.defect.params import DefectParams
    from engine.params import ReconParams

    params = ReconParams(defect=DefectParams(side="right", point_lps_mm=(1.0, 2.0, 3.0), min_volume_mm3=500.0))
    again = ReconParams.from_dict(json.loads(json.dumps(params.to_dict())))
    assert again == params and ReconParams.from_dict(ReconParams().to_dict()).defect is None
    with pytest.raises(ValueError, match="Unknown defect parameters"):
        ReconParams.from_dict({"defect": {"sides": "left"}})
