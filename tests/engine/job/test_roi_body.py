"""A region of interest through the body (issue 41): the body outline is found on the whole scan before the crop
(``engine.job.plans.prepare_whole``), so a box through the head keeps the bone inside it (on the crop alone the
outline is cut open and every piece of the skull lies "outside the body"), while a couch in the box still goes.
The same job from the CLI's flags and the API's (and the page's) params; on a generated phantom and on the real
cranium CT."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from core.params import JobParams
from engine.cli import build_parser, main
from engine.cli.args import job_spec
from engine.errors import NoBoneInBodyError
from engine.job import JobSpec, OutputSpec, resolve_runtime, run_job
from engine.job.plans import PREPARED_WHOLE, prepare_volume, prepare_whole
from engine.labels.pieces import crop_roi
from engine.params import BodyMaskParams, ReconParams, RoiParams
from engine.types import Volume
from engine.volume.bodymask import isolate_bone
from tests.conftest import shared_file
from tests.engine.volume.test_bodymask import patient_on_a_couch

CRANIUM_SPACING = (1.5, 0.9570312, 0.9570312)


def _api(**params: object) -> JobSpec:
    return JobParams.model_validate(params).job_spec()


def _phantom() -> Volume:
    from engine.data.phantom import bone_phantom

    return Volume(bone_phantom((24, 40, 40), dtype=np.int16) - np.int16(1024), (0.6, 0.5, 0.5), units="HU")


def test_the_crop_alone_has_no_body_around_its_bone() -> None:
    """The failure this fixes: half of the phantom, outlined on its own, has its bone 'outside the body'."""
    half = crop_roi(_phantom(), RoiParams(((0, 24), (0, 40), (0, 20))))
    with pytest.raises(NoBoneInBodyError, match="lie outside the body outline"):
        isolate_bone(half, 300.0, BodyMaskParams(), hu_offset=0.0)


@pytest.mark.parametrize(
    "box", [((0, 24), (0, 40), (0, 20)), ((0, 24), (0, 20), (0, 40)), ((0, 12), (0, 40), (10, 30))]
)
def test_a_box_through_the_phantom_keeps_the_bone_inside_it(tmp_path: Path, box: tuple) -> None:
    whole = _phantom()
    spec = _api(roi={"box": [list(r) for r in box]})
    result = run_job(whole, tmp_path / "out", spec, resolve_runtime("cpu"))
    sl = tuple(slice(lo, hi) for lo, hi in box)
    kept = prepare_volume(whole, spec.recon).volume.data[sl] >= 300
    assert result.volume is not None and np.array_equal(result.volume.data >= 300, kept)  # the whole's bone, cropped
    assert kept.sum() > 0.2 * (whole.data >= 300).sum()
    report = result.report
    assert report["body_mask"]["applied"] and "whole scan [24, 40, 40]" in report["body_mask"]["outlined_on"]
    assert report["input"]["shape_zyx"] == [hi - lo for lo, hi in box]
    assert report["mesh"]["watertight"] and report["mesh"]["volume_mm3"] > 0


def test_a_couch_inside_the_box_is_still_removed() -> None:
    """Half of a patient on a couch: the skull's half is kept, the couch under it goes (outlined on the whole)."""
    vol = Volume(patient_on_a_couch(holder=False), (1.0, 1.0, 1.0), units="HU")
    params = ReconParams()
    cut = crop_roi(prepare_whole(vol, params), RoiParams(((0, 20), (0, 64), (0, 32))))
    prepared = prepare_volume(cut, params)
    skull = patient_on_a_couch(couch=False, holder=False)[:, :, :32] >= 300
    np.testing.assert_array_equal(prepared.volume.data >= 300, skull)
    assert prepared.body is not None and prepared.body["pieces_removed"] == 1  # the couch, counted on the whole
    assert cut.source[PREPARED_WHOLE]["body_mask"] is prepared.body


def test_a_box_covering_the_scan_is_prepared_as_before(tmp_path: Path) -> None:
    """A roi over the whole grid changes nothing: the pipeline outlines it itself."""
    spec = _api(roi={"box": [[0, 24], [0, 40], [0, 40]]})
    result = run_job(_phantom(), tmp_path / "out", spec, resolve_runtime("cpu"))
    assert PREPARED_WHOLE not in result.report["input"]["source"] and "outlined_on" not in result.report["body_mask"]


def test_half_the_real_cranium_from_the_cli_and_the_api(tmp_path: Path) -> None:
    """The cranium CT (../shared/data, GPL-2): its left and right halves (voxels through the API's params, mm
    through the CLI) come out, and together they hold the whole model's volume (less the one-voxel gap between
    the two cut faces)."""
    scan = shared_file("cranium_ct", "cranium_ct_png16.zip")
    flags = ["--voxel-size", ",".join(map(str, CRANIUM_SPACING)), "--hu-offset", "1024", "--preset", "bone"]
    params = {"spacing": list(CRANIUM_SPACING), "hu_offset": 1024, "preset": "bone"}
    runtime = resolve_runtime("cpu")
    whole = run_job(scan, tmp_path / "whole", _api(**params), runtime).report["mesh"]["volume_mm3"]
    left_spec = _api(roi={"box": [[0, 108], [0, 256], [0, 128]]}, **params)
    cli = job_spec(
        build_parser().parse_args(["reconstruct", str(scan), "-o", "x", *flags, "--roi", "0:108,0:256,0:128"])
    )
    assert dataclasses.replace(cli, recon=left_spec.recon, outputs=OutputSpec()) == left_spec  # the page's params too
    left = run_job(scan, tmp_path / "left", left_spec, runtime).report
    assert left["body_mask"]["pieces_removed"] == 2  # the head holder's arc, found on the whole scan
    # the right half in mm (x, y, z in the patient frame): x from sample 128 on
    x0 = 128 * CRANIUM_SPACING[2] - 0.1
    out = tmp_path / "right"
    argv = [*flags, "--roi", f"{x0}:999,-999:999,-999:999", "--roi-units", "mm", "--device", "cpu", "--quiet"]
    assert main(["reconstruct", str(scan), "-o", str(out), *argv]) == 0
    right = json.loads((out / "report.json").read_text())
    assert right["input"]["source"]["roi"]["slices_zyx"] == [[0, 108], [0, 256], [128, 256]]
    halves = left["mesh"]["volume_mm3"] + right["mesh"]["volume_mm3"]
    assert 0.2 * whole < left["mesh"]["volume_mm3"] < 0.8 * whole
    assert halves == pytest.approx(whole, rel=0.01), (left["mesh"]["volume_mm3"], right["mesh"]["volume_mm3"], whole)
