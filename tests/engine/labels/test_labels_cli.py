"""``bonemesh reconstruct`` with label maps (engine.labels.cli through engine.cli.main): a NIfTI of the headsq bone
halves detected by its suffix, ``--labels`` refusing a float NIfTI, ``--pieces N`` and ``--roi`` on the bundled CT;
``labels/<name>.stl`` per label (watertight, mm, where the label's voxels are), ``labels.zip`` and the report's list.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import trimesh

from engine.cli import main
from tests.engine.labels.test_labels_util import headsq_labels


@pytest.fixture(scope="module")
def nifti(tmp_path_factory: pytest.TempPathFactory) -> Path:
    lv = headsq_labels()
    affine = np.eye(4)
    affine[:3, :3] = np.diag([-1.0, -1.0, 1.0]) @ (np.asarray(lv.direction) * np.asarray(lv.spacing_zyx_mm[::-1]))
    affine[:3, 3] = np.diag([-1.0, -1.0, 1.0]) @ np.asarray(lv.origin_mm)
    path = tmp_path_factory.mktemp("nifti") / "halves.nii.gz"
    nib.save(nib.Nifti1Image(lv.labels.transpose(2, 1, 0).astype(np.uint8), affine), str(path))
    return path


def test_a_model_per_label(nifti: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert main(["reconstruct", str(nifti), "-o", str(out), "--device", "cpu", "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    rows = report["labels"]
    assert [r["file"] for r in rows] == ["labels/label_1.stl", "labels/label_2.stl"]
    lv = headsq_labels()
    for row in rows:
        mesh = trimesh.load(out / row["file"])
        assert mesh.is_watertight and len(mesh.faces) == row["faces"]
        assert mesh.volume == pytest.approx(row["volume_mm3"], rel=1e-3)
        # the STL (LPS mm) lies on its label's voxels
        idx = np.clip(np.round(lv.index_of(mesh.vertices)).astype(int), 0, np.array(lv.labels.shape) - 1)
        assert np.mean(lv.labels[tuple(idx.T)] == row["value"]) > 0.5
    with zipfile.ZipFile(out / "labels.zip") as zf:
        assert sorted(zf.namelist()) == ["labels/label_1.stl", "labels/label_2.stl"]
    assert "label_1" in capsys.readouterr().out


def test_float_nifti_with_labels_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "ct.nii"
    nib.save(nib.Nifti1Image(np.zeros((8, 8, 8), np.float32), np.eye(4)), str(path))
    out = tmp_path / "out"
    assert main(["reconstruct", str(path), "--labels", "-o", str(out), "--device", "cpu"]) == 2
    assert "not a label map" in capsys.readouterr().err and not out.exists()


def test_pieces_and_roi_of_the_demo(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "pieces"
    args = ["reconstruct", "--demo", "--pieces", "2", "--roi", "0:60,0:64,0:64", "-o", str(out), "--device", "cpu"]
    assert main([*args, "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    rows = report["labels"]
    # the crop's second bone piece (15 voxels) meshes below the island size: a speck the model drops too, not a piece
    assert [r["name"] for r in rows] == ["piece_1"] and all(r["watertight"] for r in rows)
    assert report["pieces"]["pieces_kept"] == 1 and "2 pieces asked for, 1 found" in report["pieces"]["note"]
    assert f"bonemesh: warning: {report['pieces']['note']}" in capsys.readouterr().err  # said, not only written
    assert json.loads((out / "report.json").read_text())["input"]["shape_zyx"] == [60, 64, 64]


def test_roi_on_the_ct_pipeline(tmp_path: Path) -> None:
    out = tmp_path / "roi"
    assert main(["reconstruct", "--demo", "--roi", "0:40,0:64,0:64", "-o", str(out), "--device", "cpu", "--quiet"]) == 0
    assert json.loads((out / "report.json").read_text())["input"]["shape_zyx"] == [40, 64, 64]
    assert (
        main(["reconstruct", "--demo", "--roi", "500:600,0:64,0:64", "-o", str(tmp_path / "x"), "--device", "cpu"]) == 2
    )
