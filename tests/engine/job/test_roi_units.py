"""The roi's two orders said where the numbers are typed (issue 41): voxel indices z, y, x and mm x, y, z, in the
CLI's help for ``--roi`` and on the page beside the region's box; and a label map says what placed it (a NIfTI's
sform or qform, or its voxel sizes alone), not DICOM's headers, in report.json (which the page shows)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from engine.cli import build_parser, main
from engine.io.labelmaps import nifti_placement
from engine.orient import patient_frame
from engine.types import Volume

REPO = Path(__file__).resolve().parents[3]


def _help(option: str) -> str:
    sub = build_parser()._subparsers._group_actions[0].choices["reconstruct"]  # type: ignore[union-attr]
    action = next(a for a in sub._actions if option in a.option_strings)
    return " ".join(str(action.help).split())


def test_the_cli_help_gives_each_order() -> None:
    roi = _help("--roi")
    assert "voxel indices in z,y,x order" in roi and "mm in x,y,z order" in roi
    assert "z,y,x" in _help("--roi-units") and "x,y,z" in _help("--roi-units")


def test_a_malformed_box_names_the_order_of_its_units(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for units, order in (("voxels", "z,y,x voxel indices"), ("mm", "x,y,z in mm")):
        argv = ["reconstruct", "--demo", "-o", str(tmp_path / "x"), "--roi", "1:2", "--roi-units", units, "--quiet"]
        assert main(argv) == 2
        assert order in capsys.readouterr().err


def test_the_page_says_the_order_beside_the_box() -> None:
    html = (REPO / "service" / "static" / "index.html").read_text()
    label = re.search(r"<label>(Region:[^<]*)<input id=\"roi\"", html)
    assert label is not None, "the region's box has its label"
    text = " ".join(label.group(1).split())
    assert "z, y, x" in text and "x, y, z" in text and "voxel" in text and "mm" in text


@pytest.mark.parametrize(
    ("sform", "qform", "want"),
    [
        (2, 0, "NIfTI sform (aligned space; RAS, turned into LPS)"),
        (0, 1, "NIfTI qform (scanner space; RAS, turned into LPS)"),
        (4, 1, "NIfTI sform (MNI 152 space; RAS, turned into LPS)"),
        (0, 0, "NIfTI voxel sizes only (no qform or sform: RAS axes assumed, turned into LPS)"),
    ],
)
def test_a_nifti_label_map_says_how_it_was_placed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], sform: int, qform: int, want: str
) -> None:
    import nibabel as nib

    data = np.zeros((12, 12, 12), np.uint8)
    data[3:9, 3:9, 3:9] = 1
    img = nib.Nifti1Image(data, np.diag([2.0, 2.0, 2.0, 1.0]))
    img.set_sform(np.diag([2.0, 2.0, 2.0, 1.0]), code=sform)
    img.set_qform(np.diag([2.0, 2.0, 2.0, 1.0]), code=qform)
    path = tmp_path / "cube.nii.gz"
    nib.save(img, str(path))
    assert nifti_placement(nib.load(str(path)).header) == want
    assert main(["reconstruct", str(path), "-o", str(tmp_path / "out"), "--device", "cpu", "--quiet"]) == 0, (
        capsys.readouterr().err
    )
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["frame"]["placed_by"] == want and "ImagePositionPatient" not in json.dumps(report)


def test_a_placed_volume_says_what_placed_it() -> None:
    """A DICOM series (no words of its own) is placed by its headers; a map that says how, by those words."""
    data = np.zeros((2, 2, 2), np.uint8)
    assert patient_frame(Volume(data, (1, 1, 1), patient_frame=True)).placed_by.startswith("DICOM")
    placed = Volume(data, (1, 1, 1), patient_frame=True, source={"placed_by": "NRRD space directions (LPS)"})
    assert patient_frame(placed).placed_by == "NRRD space directions (LPS)"
