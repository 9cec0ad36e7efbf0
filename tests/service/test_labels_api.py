"""Segmentations through the API and a real worker (issue 30): a NIfTI label map of the headsq bone halves becomes a
label job (model.glb / phone.glb with a named node per label, labels.zip with a watertight STL per label, the report's
list); a CT with ``pieces`` and ``roi`` gets its largest bone pieces as parts; bad ``pieces`` / ``roi`` are refused
with 422 and a float NIfTI with 422, before any upload is kept."""

from __future__ import annotations

import io
import json
import zipfile

import httpx
import nibabel as nib
import numpy as np
import pytest
import trimesh

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.export.files import engine_files
from tests.engine.labels.test_labels_outputs import nifti_bytes, seg_zip
from tests.engine.labels.test_labels_util import headsq_labels
from tests.service.procs import ServiceStack, submit, wait_for_job

SMALL = {"phone_max_triangles": 3000, "ar_max_triangles": 1200}


def _nodes(data: bytes) -> list[str]:
    n = int.from_bytes(data[12:16], "little")
    return [node["name"] for node in json.loads(data[20 : 20 + n])["nodes"]]


def test_a_label_map_gets_a_model_per_label(stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client) -> None:
    resp = submit(client_a, nifti_bytes(headsq_labels()), SMALL, filename="halves.nii.gz")
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=180)
    assert job["state"] == "succeeded", json.dumps(job)
    outs = {o["name"]: o for o in job["outputs"]}
    assert list(outs) == list(engine_files(labels=True)) and outs["labels.zip"]["kind"] == "labels"
    files = {name: anon.get(o["url"]).content for name, o in outs.items()}
    report = json.loads(files["report.json"])
    names = [r["name"] for r in report["labels"]]
    assert names == ["label_1", "label_2"]  # a plain NIfTI names no segment
    assert _nodes(files["model.glb"]) == _nodes(files["phone.glb"]) == _nodes(files["ar.glb"]) == names
    total = sum(r["faces"] for r in report["labels"])
    assert outs["model.glb"]["triangles"] == outs["labels.zip"]["triangles"] == total
    assert outs["phone.glb"]["triangles"] <= 1.1 * SMALL["phone_max_triangles"]
    with zipfile.ZipFile(io.BytesIO(files["labels.zip"])) as zf:
        assert sorted(zf.namelist()) == ["labels/label_1.stl", "labels/label_2.stl"]
        for row in report["labels"]:
            mesh = trimesh.load(io.BytesIO(zf.read(row["file"])), file_type="stl")
            assert mesh.is_watertight and mesh.volume == pytest.approx(row["volume_mm3"], rel=1e-3)
            assert row["volume_mm3"] > 1000 and row["faces"] == len(mesh.faces)
            one = client_a.get(f"/v1/jobs/{job['id']}/labels/{row['value']}.stl")  # one label, out of the zip
            assert one.status_code == 200 and one.content == zf.read(row["file"]), one.text
            assert (
                one.headers["content-type"] == "model/stl"
                and f'"{row["name"]}.stl"' in one.headers["content-disposition"]
            )
    missing = client_a.get(f"/v1/jobs/{job['id']}/labels/7.stl")
    assert missing.status_code == 404 and "1 'label_1', 2 'label_2'" in missing.json()["detail"], missing.text
    assert anon.get(f"/v1/jobs/{job['id']}/labels/1.stl").status_code == 401
    # placed by its label map: a turn is refused at once (409, the worker would refuse it too), the files unchanged
    resp = client_a.post(f"/v1/jobs/{job['id']}/orient", json={"first_slice": "inferior"})
    assert resp.status_code == 409 and "label" in resp.json()["detail"], resp.text


def test_a_dicom_seg_with_its_ct(stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client) -> None:
    """A DICOM SEG zipped with its CT series: a label job with the SEG's segment names; zipped without its CT, refused
    before it is queued."""
    resp = submit(client_a, seg_zip(), SMALL, filename="study.zip")
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=180)
    assert job["state"] == "succeeded", json.dumps(job)
    outs = {o["name"]: o for o in job["outputs"]}
    assert _nodes(anon.get(outs["model.glb"]["url"]).content) == ["right half", "left half"]
    resp = submit(client_a, seg_zip(with_ct=False), SMALL, filename="seg_only.zip")
    assert (
        resp.status_code == 422 and "seg_only.zip holds a DICOM SEG without the CT series it was drawn on" in resp.text
    ), resp.text


def test_pieces_of_a_cropped_ct(stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client) -> None:
    params = {
        "iso": HEADSQ_LEVEL,
        "spacing": list(HEADSQ_SPACING_ZYX_MM),
        "pieces": 2,
        "roi": {"box": [[70, 93], [0, 64], [0, 64]], "units": "voxels"},  # the crop cuts the skull in two
        **SMALL,
    }
    resp = submit(client_a, HEADSQ_ZIP, params)
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=180)
    assert job["state"] == "succeeded", json.dumps(job)
    outs = {o["name"]: o for o in job["outputs"]}
    report = anon.get(outs["report.json"]["url"]).json()
    assert report["input"]["shape_zyx"] == [23, 64, 64]  # cropped before anything ran
    assert [r["name"] for r in report["labels"]] == ["piece_1", "piece_2"]
    assert report["labels"][0]["volume_mm3"] > report["labels"][1]["volume_mm3"]
    assert _nodes(anon.get(outs["model.glb"]["url"]).content) == ["piece_1", "piece_2"]


@pytest.mark.parametrize(
    "params",
    [
        {"pieces": 0},
        {"pieces": "two"},
        {"roi": {"box": [[0, 10], [0, 10]]}},
        {"roi": {"box": [[10, 0], [0, 10], [0, 10]]}},
        {"roi": {"box": [[0.5, 10], [0, 10], [0, 10]]}},
        {"roi": {"box": [[0, 10], [0, 10], [0, 10]], "units": "cm"}},
        {"pieces": 2, "labels": True},
        {"pieces": 2, "defect": {}},
    ],
)
def test_bad_pieces_or_roi_are_refused(client_a: httpx.Client, params: dict) -> None:
    resp = submit(client_a, b"not read", params)
    assert resp.status_code == 422, resp.text
    assert any(word in resp.text for word in ("pieces", "roi", "labels")), resp.text


def test_a_float_nifti_is_refused_as_labels(client_a: httpx.Client) -> None:
    data = nib.Nifti1Image(np.random.default_rng(0).random((8, 8, 8), np.float32), np.eye(4)).to_bytes()
    for params in ({"labels": True}, {}):
        resp = submit(client_a, data, params, filename="ct.nii")
        assert resp.status_code == 422, resp.text
        assert "not a label map" in resp.json()["detail"] and "ct.nii" in resp.json()["detail"]
    resp = submit(client_a, nifti_bytes(headsq_labels()), {"pieces": 2}, filename="halves.nii.gz")
    assert resp.status_code == 422 and "label map" in resp.json()["detail"], resp.text
    with_png = io.BytesIO()
    with zipfile.ZipFile(with_png, "w") as zf:
        zf.writestr("notes.txt", "no label map here")
    resp = submit(client_a, with_png.getvalue(), {"labels": True}, filename="notes.zip")
    assert resp.status_code == 422 and "no label map" in resp.json()["detail"], resp.text


@pytest.mark.browser
def test_the_page_lists_the_labels_and_hides_one(stack: ServiceStack, client_a: httpx.Client, tmp_path) -> None:
    """A label map picked on the page, with a region: the job is cropped to it; the result lists each label (name,
    colour) with a checkbox; unticking one cuts its node's material away in <model-viewer> (alpha mask), ticking it
    shows it again. A malformed region is refused on the page, naming the field."""
    from selenium.webdriver.common.by import By

    from tests.service.browser import find_chromium, open_page_with_file, start_chromium
    from tests.service.procs import wait_until

    paths = find_chromium()
    if isinstance(paths, str):
        pytest.skip(paths)
    seg = tmp_path / "halves.nii.gz"
    seg.write_bytes(nifti_bytes(headsq_labels()))
    driver = start_chromium(*paths, tmp_path)
    try:
        open_page_with_file(driver, stack.base_url, seg)
        driver.find_element(By.ID, "roi").send_keys("0:60, 0:64")
        driver.find_element(By.ID, "start").click()
        assert "Region: give three ranges" in driver.find_element(By.ID, "upload-text").text
        driver.find_element(By.ID, "roi").send_keys(", 0:64")
        driver.find_element(By.ID, "start").click()
        box = driver.find_element(By.ID, "labels-box")
        wait_until(lambda: box.get_attribute("data-count") == "2", 180, "the labels' list")
        viewer = "document.getElementById('viewer')"
        wait_until(lambda: driver.execute_script(f"return {viewer}.dataset.loaded"), 120, "the model")
        names = driver.execute_script(f"return {viewer}.model.materials.map((m) => m.name)")
        assert names == ["label_1", "label_2"], names
        checks = box.find_elements(By.CSS_SELECTOR, "input[type=checkbox]")
        assert [c.get_attribute("data-label") for c in checks] == names and "label_2" in box.text
        alpha = f"return {viewer}.model.getMaterialByName('label_2').pbrMetallicRoughness.baseColorFactor[3]"
        mode = f"return {viewer}.model.getMaterialByName('label_2').getAlphaMode()"
        checks[1].click()
        assert driver.execute_script(alpha) == 0 and driver.execute_script(mode) == "MASK"
        checks[1].click()
        assert driver.execute_script(alpha) == 1 and driver.execute_script(mode) == "OPAQUE"
        # each label has its own STL download (the API's labels/{value}.stl, fetched with the key)
        links = box.find_elements(By.CSS_SELECTOR, "a[data-stl]")
        assert [a.get_attribute("data-stl") for a in links] == ["1", "2"]
        got = driver.execute_async_script(
            "const done = arguments[arguments.length - 1];"
            "labelStl(document.getElementById('job-id').textContent, 2).then((b) => b.arrayBuffer())"
            ".then((a) => done(a.byteLength), (e) => done(String(e)));"
        )
        assert isinstance(got, int) and got > 84 and (got - 84) % 50 == 0, got  # a binary STL: header + 50 B a face
        assert not driver.find_element(By.ID, "turn-over").is_displayed()  # placed by its label map
        job = client_a.get(f"/v1/jobs/{driver.find_element(By.ID, 'job-id').text}").json()
        assert job["params"]["roi"] == {"box": [[0, 60], [0, 64], [0, 64]], "units": "voxels"}
        report = httpx.get(next(o["url"] for o in job["outputs"] if o["kind"] == "report")).json()
        assert report["input"]["shape_zyx"] == [60, 64, 64]
    finally:
        driver.quit()
