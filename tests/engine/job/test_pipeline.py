"""engine.reconstruct and write_outputs end to end: stages' invariants, report, files, failures."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from engine.data import HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.errors import InputError
from engine.io.stack import load_slice_zip
from engine.job.outputs import write_outputs
from engine.params import DecimateParams, IslandParams, IsoParams, ReconParams, SmoothParams
from engine.job.pipeline import STAGES, EmptySurfaceError, reconstruct
from engine.types import Volume
from tests.engine.meshutil import assert_closed_manifold, signed_volume
from tests.engine.scans import scan_file

pytestmark = pytest.mark.both_backends  # device tests run on Warp's CPU and on OpenCL (tests/conftest.py)

HEADSQ_PARAMS = ReconParams(iso=IsoParams(iso=1150.0))


@pytest.fixture(scope="module")
def headsq() -> Volume:
    return Volume(load_slice_zip(HEADSQ_ZIP), HEADSQ_SPACING_ZYX_MM)


@pytest.fixture(scope="module")
def headsq_recon(headsq):
    return reconstruct(headsq, HEADSQ_PARAMS, device="cpu")


def test_reconstruct_defaults_follow_the_paper(headsq_recon):
    rep = headsq_recon.report
    mesh = headsq_recon.mesh
    assert list(rep["stage_seconds"]) == list(STAGES)
    mc = rep["counts"]["isosurface"]["faces"]
    assert abs(len(mesh.faces) / mc - 0.2) < 0.2 * 0.05  # reduction factor 0.2 within 5 %
    assert_closed_manifold(mesh.vertices, mesh.faces)
    assert rep["mesh"]["watertight"] and rep["mesh"]["n_faces"] == len(mesh.faces)
    assert signed_volume(mesh.vertices, mesh.faces) > 0
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, rtol=1e-4)
    assert rep["iso_level"] == {
        "value": 1150.0, "units": "raw", "chosen_by": "given", "hu_offset": None, "hu_offset_from": None
    }  # fmt: skip
    json.dumps(rep, default=str)


def test_decimation_and_smoothing_keep_the_volume(headsq):
    """Against the MC33 surface of the Gaussian-smoothed volume, the final model keeps its volume."""
    base = reconstruct(headsq, ReconParams(iso=IsoParams(iso=1150.0), decimate=None, smooth=None), device="cpu")
    final = reconstruct(headsq, HEADSQ_PARAMS, device="cpu")
    v0 = signed_volume(base.mesh.vertices, base.mesh.faces)
    v1 = signed_volume(final.mesh.vertices, final.mesh.faces)
    assert abs(v1 / v0 - 1) < 0.01
    smoothed = reconstruct(headsq, ReconParams(iso=IsoParams(iso=1150.0), decimate=None), device="cpu")
    assert abs(signed_volume(smoothed.mesh.vertices, smoothed.mesh.faces) / v0 - 1) < 0.005


@pytest.mark.parametrize(
    ("folder", "name", "spacing"),
    [
        ("cranium_ct", "cranium_ct_png16.zip", (1.5, 0.957, 0.957)),
        ("pelvis_ct", "pelvis_ct_png16.zip", (5.0, 1.663, 1.663)),
    ],
)
def test_default_smoothing_keeps_volume_on_real_scans(folder, name, spacing):
    vol = Volume(load_slice_zip(scan_file(folder, name)), spacing)
    iso = IsoParams(preset="bone", hu_offset=1024.0)
    plain = reconstruct(vol, ReconParams(iso=iso, smooth=None), device="cpu")
    smooth = reconstruct(vol, ReconParams(iso=iso), device="cpu")
    np.testing.assert_array_equal(plain.mesh.faces, smooth.mesh.faces)
    change = (
        signed_volume(smooth.mesh.vertices, smooth.mesh.faces) / signed_volume(plain.mesh.vertices, plain.mesh.faces)
        - 1
    )
    assert abs(change) < 0.005
    assert smooth.report["mesh"]["watertight"]


def test_island_removal_and_max_triangles(headsq):
    params = ReconParams(
        iso=IsoParams(iso=1150.0),
        islands=IslandParams(keep_largest=1),
        decimate=DecimateParams(reduction=None, max_triangles=5000),
        smooth=SmoothParams(iterations=2),
    )
    recon = reconstruct(headsq, params, device="cpu")
    assert recon.report["mesh"]["components"] == 1
    assert len(recon.mesh.faces) <= 5000 or recon.report["decimate"].get("limited_by_watertightness")


def test_empty_surface_is_an_input_error(headsq):
    with pytest.raises(EmptySurfaceError, match="no surface"):
        reconstruct(headsq, ReconParams(iso=IsoParams(iso=1e6)), device="cpu")
    assert issubclass(EmptySurfaceError, InputError)


def test_progress_is_reported(headsq):
    seen = []
    reconstruct(headsq, HEADSQ_PARAMS, device="cpu", on_progress=lambda s, f: seen.append((s, f)))
    assert seen[0] == ("preprocess", 0.0) and seen[-1] == ("normals", 1.0)
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions)


# ------------------------------------------------------------------------------------------- outputs
def test_write_outputs(headsq_recon, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    import DracoPy

    paths = write_outputs(headsq_recon, tmp_path, HEADSQ_PARAMS, device="cpu")
    assert set(paths) == {
        *("model.stl", "model.glb", "phone.glb", "ar.glb", "report.json"),
        *("phone_meshopt.glb", "model.usdz", "preview.png"),
    }
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(paths)  # no temporary leftovers
    stl = trimesh.load(paths["model.stl"])
    assert stl.is_watertight and len(stl.faces) == len(headsq_recon.mesh.faces)
    mm = headsq_recon.mesh.vertices[:, ::-1]
    np.testing.assert_allclose(stl.extents, mm.max(axis=0) - mm.min(axis=0), rtol=1e-5)
    glb = trimesh.load(io.BytesIO(paths["model.glb"].read_bytes()), file_type="glb").to_geometry()
    np.testing.assert_allclose(sorted(glb.extents), sorted(stl.extents / 1000.0), rtol=1e-4)  # metres
    assert glb.volume > 0
    phone = json.loads(
        paths["phone.glb"].read_bytes()[20 : 20 + int.from_bytes(paths["phone.glb"].read_bytes()[12:16], "little")]
    )
    assert "KHR_draco_mesh_compression" in phone["extensionsRequired"]
    assert phone["accessors"][phone["meshes"][0]["primitives"][0]["indices"]]["count"] // 3 <= 100_000
    ar = trimesh.load(io.BytesIO(paths["ar.glb"].read_bytes()), file_type="glb").to_geometry()
    assert len(ar.faces) <= 50_000
    report = json.loads(paths["report.json"].read_text())
    for key in ("parameters", "device", "versions", "stage_seconds", "counts", "mesh", "exports"):
        assert key in report
    for key in ("watertight", "manifold", "components", "euler", "volume_mm3", "area_mm2", "bbox_mm"):
        assert key in report["mesh"]
    assert DracoPy  # imported: the decoder is available for the app-side check


def test_failed_export_leaves_no_partial_model(headsq_recon, tmp_path, monkeypatch):
    import engine.export.draco

    def broken(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(engine.export.draco, "to_draco_glb", broken)  # the registry's exporter of phone.glb
    with pytest.raises(RuntimeError, match="disk full"):
        write_outputs(headsq_recon, tmp_path, HEADSQ_PARAMS, device="cpu")
    assert list(tmp_path.iterdir()) == []


def test_phone_budget_is_met_on_a_speckled_scan(tmp_path):
    """Specks cannot be decimated below a tetrahedron each: the phone/AR copies drop the smallest pieces."""
    from engine.params import ExportParams

    rng = np.random.default_rng(4)
    z, y, x = np.indices((40, 48, 48), dtype=np.float32)
    vol = (14 - np.sqrt((z - 20) ** 2 + (y - 24) ** 2 + (x - 24) ** 2)) * 100
    specks = rng.integers(2, 38, size=(400, 3))
    specks = specks[np.linalg.norm(specks - [20, 24, 24], axis=1) > 18]
    vol[specks[:, 0], specks[:, 1], specks[:, 2]] = 500.0
    volume = Volume(vol.astype(np.float32), (1.0, 1.0, 1.0))
    params = ReconParams(  # speck removal off: the budget logic is what is tested
        iso=IsoParams(iso=0.0), gaussian=None, islands=None,
        export=ExportParams(phone_max_triangles=600, ar_max_triangles=300),
    )  # fmt: skip
    recon = reconstruct(volume, params, device="cpu")
    assert recon.report["mesh"]["components"] > 100
    write_outputs(recon, tmp_path, params, device="cpu")
    exports = recon.report["exports"]
    assert exports["phone.glb"]["faces"] <= 600 and exports["ar.glb"]["faces"] <= 300
    assert exports["phone.glb"]["pieces_dropped"] > 0 and not exports["phone.glb"]["over_budget"]


def test_nan_in_the_volume_is_an_input_error():
    vol = np.zeros((8, 8, 8), np.float32)
    vol[2:6, 2:6, 2:6] = 1.0
    vol[4, 4, 4] = np.nan
    with pytest.raises(InputError, match="NaN"):
        reconstruct(Volume(vol, (1.0, 1.0, 1.0)), ReconParams(iso=IsoParams(iso=0.5)), device="cpu")


def test_phone_budget_is_met_on_a_piece_of_high_genus(tmp_path):
    """A perforated plate (one piece, 144 tunnels) cannot shrink far under the topology guard: the phone and AR
    copies are decimated without it, and the print model keeps every tunnel."""
    from engine.params import ExportParams

    z, y, x = np.indices((20, 100, 100), dtype=np.float32)
    plate = np.minimum(4.5 - np.abs(z - 10), 45 - np.maximum(np.abs(y - 50), np.abs(x - 50)))
    holes = 2.2 - np.hypot((y - 50 + 33) % 6 - 3, (x - 50 + 33) % 6 - 3)  # a 12 x 12 grid of 2.2-voxel holes
    holes[:, (np.abs(np.arange(100) - 50) > 35), :] = -1
    holes[:, :, (np.abs(np.arange(100) - 50) > 35)] = -1
    vol = np.minimum(plate, -holes) * 100
    params = ReconParams(
        iso=IsoParams(iso=0.0), gaussian=None, export=ExportParams(phone_max_triangles=1000, ar_max_triangles=500)
    )
    recon = reconstruct(Volume(vol.astype(np.float32), (1.0, 1.0, 1.0)), params, device="cpu")
    mesh = recon.report["mesh"]
    assert mesh["components"] == 1 and mesh["watertight"] and mesh["euler"] <= 2 - 2 * 100  # genus >= 100
    write_outputs(recon, tmp_path, params, device="cpu")
    exports = recon.report["exports"]
    assert exports["phone.glb"]["faces"] <= 1000 and exports["ar.glb"]["faces"] <= 500
    assert exports["phone.glb"]["topology_preserved"] is False and not exports["phone.glb"]["over_budget"]
    assert recon.report["mesh"]["euler"] == mesh["euler"]  # the print model is untouched
