"""engine.job.reorient: a finished model placed in another stack orientation gives the files that reconstructing with
that orientation gives, up to float rounding; the report records the new frame; a DICOM model is refused."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from engine.errors import InputError
from engine.export.glb import read_glb
from engine.export.stl import from_stl
from engine.isosurface import marching_cubes_33
from engine.job.outputs import write_outputs
from engine.job.pipeline import Reconstruction, reconstruct
from engine.job.reorient import reorient
from engine.params import IsoParams, OrientParams, ReconParams
from engine.types import Mesh
from tests.engine.cli.test_orient import SPACING, marked_volume

TURNED = OrientParams(first_slice="inferior", flip_ap=True)  # the cranium's fix: a half turn about left-right
MIRRORED = OrientParams(flip_lr=True)


def _written(orient: OrientParams, folder):
    params = ReconParams(iso=IsoParams(iso=0.5), orient=orient)
    recon = reconstruct(marked_volume(), params, device="cpu")
    return write_outputs(recon, folder, params, device="cpu")


def _facets(path):
    data = path.read_bytes()
    v, f = from_stl(data)
    tri = v[:, ::-1][f]  # (F, 3, 3) corners, x, y, z
    return np.sort(np.round(tri.reshape(len(f), 9), 3), axis=0), data[:80]


@pytest.mark.parametrize("orient", [TURNED, MIRRORED])
def test_reorienting_equals_reconstructing_with_those_params(tmp_path, orient):
    default = _written(OrientParams(), tmp_path / "default")
    direct = _written(orient, tmp_path / "direct")
    before = json.loads(default["report.json"].read_text())
    (tmp_path / "first.stl").write_bytes(default["model.stl"].read_bytes())
    paths = reorient(tmp_path / "default", orient, device="cpu")
    assert set(paths) == set(direct)  # every output re-published
    got, want = _facets(paths["model.stl"]), _facets(direct["model.stl"])
    np.testing.assert_allclose(got[0], want[0], atol=2e-3)  # the same print model, in the new frame
    gp, gn, gt = read_glb(paths["model.glb"].read_bytes())
    dp, dn, dt = read_glb(direct["model.glb"].read_bytes())
    np.testing.assert_allclose(gp, dp, atol=1e-6)  # metres: the same vertices, order and centre
    np.testing.assert_allclose(gn, dn, atol=1e-4)
    np.testing.assert_array_equal(gt, dt)  # and the same (outward) winding
    report = json.loads(paths["report.json"].read_text())
    wanted = json.loads(direct["report.json"].read_text())
    np.testing.assert_allclose(report["frame"]["patient_from_grid_xyz"], wanted["frame"]["patient_from_grid_xyz"])
    np.testing.assert_allclose(report["frame"]["gltf_centre_lps_mm"], wanted["frame"]["gltf_centre_lps_mm"], atol=1e-4)
    assert report["frame"]["placed_by"] == wanted["frame"]["placed_by"]
    assert report["parameters"]["orient"] == wanted["parameters"]["orient"]
    assert report["reoriented"]["from"] == before["parameters"]["orient"]
    assert report["mesh"] == before["mesh"] and report["iso_level"] == before["iso_level"]  # the rest is kept
    for name in ("phone.glb", "ar.glb", "model.usdz", "preview.png", "phone_meshopt.glb"):
        assert report["exports"][name]["bytes"] == paths[name].stat().st_size
    assert not [p for p in (tmp_path / "default").iterdir() if p.name.startswith(".")]  # no temporary folder left
    # back again: the first files
    again = reorient(tmp_path / "default", OrientParams(), device="cpu")
    np.testing.assert_allclose(_facets(again["model.stl"])[0], _facets(tmp_path / "first.stl")[0], atol=2e-3)


def test_a_dicom_model_is_refused(tmp_path):
    vol = marked_volume()
    v, f = marching_cubes_33(vol.data, 0.5, spacing=SPACING, device="cpu", closed=True)
    frame = {"placed_by": "DICOM ImagePositionPatient/Orientation", "patient_from_grid_xyz": np.eye(4).tolist()}
    report = {"frame": {**frame, "stl": "", "gltf": ""}}
    write_outputs(Reconstruction(Mesh(v, f), report), tmp_path, device="cpu")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="DICOM"):
        reorient(tmp_path, TURNED, device="cpu")
    with pytest.raises(InputError, match=r"report\.json"):
        reorient(tmp_path / "nothing", TURNED, device="cpu")


def test_a_label_jobs_folder_is_refused_as_one(tmp_path):
    """A label job's files (``labels`` in its report) are placed by its label map: refused saying so, not as a
    missing print model."""
    from engine.job import InputSpec, JobSpec, resolve_runtime, run_job
    from tests.engine.labels.test_labels_outputs import nifti_bytes
    from tests.engine.labels.test_labels_util import headsq_labels

    (tmp_path / "map.nii.gz").write_bytes(nifti_bytes(headsq_labels()))
    spec = JobSpec(recon=ReconParams.from_dict({"export": {"phone_max_triangles": 2000, "ar_max_triangles": 800}}))
    run_job(
        tmp_path / "map.nii.gz", tmp_path / "out", dataclasses.replace(spec, input=InputSpec()), resolve_runtime("cpu")
    )
    with pytest.raises(InputError, match="label job's models are placed by their label map"):
        reorient(tmp_path / "out", TURNED, device="cpu")


def test_cli_orient_command(tmp_path, capsys):
    from engine.cli import main

    _written(OrientParams(), tmp_path)
    assert main(["orient", str(tmp_path), "--first-slice", "inferior", "--flip-ap", "--device", "cpu"]) == 0
    assert "first slice inferior" in capsys.readouterr().out
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["parameters"]["orient"] == {"first_slice": "inferior", "flip_lr": False, "flip_ap": True}
    assert report["frame"]["placed_by"].startswith("image stack convention: first slice inferior")
    assert main(["orient", str(tmp_path / "missing"), "--device", "cpu"]) == 2
