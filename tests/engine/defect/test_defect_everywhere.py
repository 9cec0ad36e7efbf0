"""The same defect from every way of asking (issue 42, on issue 40's one job): ``bonemesh defect``, ``bonemesh
reconstruct --defect`` and a job with ``"defect": {}`` (``engine.job.run_job``, as the worker runs it) find it on the
scan as the model sees it (``engine.job.plans.prepare_volume``) at the model's level, and say in defect.json what
it was measured on."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.params import OrientParams

SIZE = "z={},y={},x={}".format(*HEADSQ_SPACING_ZYX_MM)


@pytest.fixture(scope="module")
def cut_scan(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """headsq with a 30 mm trephination at the right temple, as a .npy scan."""
    from engine.defect.synthetic import cut_defect
    from engine.io import load_volume

    headsq = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    orient = OrientParams(first_slice="superior")
    cut = cut_defect(headsq, HEADSQ_LEVEL, (-1.0, -0.1, 0.0), 30.0, slices=(4, 18), orient=orient)
    path = tmp_path_factory.mktemp("cut") / "cut.npy"
    np.save(path, cut.volume.data)
    return path


def test_the_cli_reconstruct_and_a_job_give_the_same_defect(cut_scan: Path, tmp_path: Path) -> None:
    from core.params import JobParams
    from engine.cli import main
    from engine.job import resolve_runtime, run_job

    common = [str(cut_scan), "--voxel-size", SIZE, "--iso", str(HEADSQ_LEVEL), "--device", "cpu"]
    assert main(["defect", *common, "-o", str(tmp_path / "defect")]) == 0
    assert main(["reconstruct", *common, "-o", str(tmp_path / "reconstruct"), "--defect", "--quiet"]) == 0
    spec = JobParams.model_validate(
        {"iso": HEADSQ_LEVEL, "spacing": list(HEADSQ_SPACING_ZYX_MM), "defect": {}}
    ).job_spec()
    run_job(cut_scan, tmp_path / "job", spec, resolve_runtime("cpu"))

    docs = {
        name: _untimed(json.loads((tmp_path / name / "defect.json").read_text()))
        for name in ("defect", "reconstruct", "job")
    }
    implants = {name: (tmp_path / name / "implant.stl").read_bytes() for name in docs}
    first: dict = docs["defect"]  # type: ignore[assignment]
    assert first["found"] is True and first["defect"]["side"] == "right"
    for name, doc in docs.items():
        assert doc["defect"] == first["defect"], name  # volume, area, slices, rim gap: the same numbers
        assert doc["implant"] == first["implant"] and doc["plane"] == first["plane"], name
        assert implants[name] == implants["defect"], name  # the same template, byte for byte
        assert doc["measured_on"] == first["measured_on"], name
    on = first["measured_on"]
    assert on["orientation"] == {"first_slice": "superior", "flip_lr": False, "flip_ap": False}
    assert on["level"]["value"] == pytest.approx(HEADSQ_LEVEL) and on["level"]["chosen_by"]
    assert on["scan"] in ("bone inside the body outline", "the whole scan")
    report = json.loads((tmp_path / "job" / "report.json").read_text())
    assert report["defect"]["measured_on"] == on and report["defect"]["volume_mm3"] == first["defect"]["volume_mm3"]


def _untimed(doc: object) -> object:
    """A document without its ``seconds`` (how long each part took: the only thing allowed to differ)."""
    if isinstance(doc, dict):
        return {k: _untimed(v) for k, v in doc.items() if k != "seconds"}
    if isinstance(doc, list):
        return [_untimed(v) for v in doc]
    return doc


def test_reconstruct_defect_flags_are_checked_like_the_api(tmp_path: Path) -> None:
    """``--defect`` with pieces or labels is refused as the API refuses ``defect`` with them (one rule)."""
    from engine.cli import main

    assert main(["reconstruct", "--demo", "-o", str(tmp_path / "o"), "--defect", "--pieces", "2"]) == 2
    assert not (tmp_path / "o").exists()
