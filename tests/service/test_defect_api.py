"""The defect through the API and a real worker (``"defect"`` in a job's params, issue 31): a skull with a
one-sided hole gets ``implant.stl`` and ``defect.json`` beside its model, the template as its own node of the GLB
files; a skull without one gets a clear answer (``found: false`` and why) and no implant; such a job is not
re-oriented; bad defect params are refused with 422 before any upload is kept."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import numpy as np
import pytest

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.export.stl import from_stl
from engine.params import OrientParams
from tests.service.conftest import slice_zip
from tests.service.procs import ServiceStack, submit, wait_for_job

PARAMS = {"iso": HEADSQ_LEVEL, "spacing": list(HEADSQ_SPACING_ZYX_MM), "orient": {"first_slice": "superior"}}


@pytest.fixture(scope="module")
def trephined() -> bytes:
    """The bundled headsq head with a 30 mm hole in the patient's left temple, as a PNG slice zip."""
    from engine.defect.synthetic import cut_defect
    from engine.io import load_volume

    volume = load_volume(HEADSQ_ZIP, spacing_zyx_mm=HEADSQ_SPACING_ZYX_MM)
    cut = cut_defect(volume, HEADSQ_LEVEL, (1.0, -0.1, 0.0), 30.0, slices=(4, 18), orient=OrientParams("superior"))
    return slice_zip(np.asarray(cut.volume.data, np.uint16))


def _glb_nodes(data: bytes) -> list[str]:
    n = int.from_bytes(data[12:16], "little")
    return [node["name"] for node in json.loads(data[20 : 20 + n])["nodes"]]


def test_a_job_with_defect_gets_its_template_and_measures(
    stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client, trephined: bytes
) -> None:
    resp = submit(client_a, trephined, {**PARAMS, "defect": {}})
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=180)
    assert job["state"] == "succeeded", json.dumps(job)
    outs = {o["name"]: o for o in job["outputs"]}
    assert outs["implant.stl"]["kind"] == "implant" and outs["defect.json"]["kind"] == "defect"
    files = {name: anon.get(o["url"]).content for name, o in outs.items()}
    verts, faces = from_stl(files["implant.stl"])
    assert outs["implant.stl"]["triangles"] == len(faces) > 100
    info = json.loads(files["defect.json"])
    assert info["found"] is True and info["defect"]["side"] == "left" and info["defect"]["volume_mm3"] > 1000
    assert _glb_nodes(files["model.glb"]) == _glb_nodes(files["phone.glb"]) == ["bone", "defect template"]
    # the template lies with the model in one frame: within the skull's box (mirrored bone may stand out of it by
    # the two sides' asymmetry: two voxels here), on the patient's left (+x in LPS)
    skull = from_stl(files["model.stl"])[0]
    slack = 2 * np.array(HEADSQ_SPACING_ZYX_MM)
    assert np.all(verts.min(axis=0) >= skull.min(axis=0) - slack), (verts.min(axis=0), skull.min(axis=0))
    assert np.all(verts.max(axis=0) <= skull.max(axis=0) + slack), (verts.max(axis=0), skull.max(axis=0))
    assert verts[:, 2].mean() > skull[:, 2].mean()
    resp = client_a.post(f"/v1/jobs/{job['id']}/orient", json={"first_slice": "inferior"})
    assert resp.status_code == 409 and "defect template" in resp.json()["detail"]


def test_a_job_on_an_intact_side_says_why_and_has_no_implant(
    stack: ServiceStack, client_a: httpx.Client, anon: httpx.Client, trephined: bytes
) -> None:
    resp = submit(client_a, trephined, {**PARAMS, "defect": {"side": "right"}})  # the hole is on the left
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client_a, resp.json()["id"], stack=stack, timeout=180)
    assert job["state"] == "succeeded", json.dumps(job)
    outs = {o["name"]: o for o in job["outputs"]}
    assert "implant.stl" not in outs and "model.stl" in outs
    info = anon.get(outs["defect.json"]["url"]).json()
    keys = {"format": info["format"], "found": False, "code": "no_defect", "message": info["message"]}
    assert info == {**keys, "measured_on": info["measured_on"]}
    assert "right side" in info["message"]
    assert set(info["measured_on"]) == {"orientation", "level", "scan"}  # what the answer was measured on


@pytest.mark.parametrize(
    "defect",
    [{"side": "up"}, {"point_lps_mm": [1, 2]}, {"point_radius_mm": 0}, {"max_faces": 10}, {"sides": "left"}],
)
def test_bad_defect_params_are_refused(client_a: httpx.Client, defect: dict) -> None:
    resp = submit(client_a, b"not read", {**PARAMS, "defect": defect})
    assert resp.status_code == 422, resp.text
    assert "defect" in resp.text


@pytest.mark.browser
def test_the_page_asks_for_the_defect_and_shows_its_template(
    stack: ServiceStack, trephined: bytes, tmp_path: Path
) -> None:
    """The page's "Bone defect" option sends ``"defect"``; the result shows the template (its own material in
    the 3D view), its size, and no turn buttons."""
    from selenium.webdriver.common.by import By

    from tests.service.browser import find_chromium, open_page_with_file, start_chromium
    from tests.service.procs import wait_until

    paths = find_chromium()
    if isinstance(paths, str):
        pytest.skip(paths)
    scan = tmp_path / "trephined.zip"
    scan.write_bytes(trephined)
    driver = start_chromium(*paths, tmp_path)
    try:
        open_page_with_file(driver, stack.base_url, scan)
        driver.execute_script(
            "document.getElementById('level-kind').value = 'iso';"
            "document.getElementById('iso').value = arguments[0];"
            "document.getElementById('spacing').value = arguments[1];",
            str(HEADSQ_LEVEL),
            ", ".join(str(v) for v in HEADSQ_SPACING_ZYX_MM),
        )
        driver.find_element(By.ID, "defect").click()
        driver.find_element(By.ID, "start").click()
        box = driver.find_element(By.ID, "defect-text")
        wait_until(lambda: box.get_attribute("data-found") in ("yes", "no"), 300, "the defect's answer")
        assert box.get_attribute("data-found") == "yes", box.text
        assert box.text.startswith("Defect template (blue): the patient's left") and "mm³" in box.text
        viewer = "document.getElementById('viewer')"
        wait_until(lambda: driver.execute_script(f"return {viewer}.dataset.loaded"), 120, "the model")
        names = driver.execute_script(f"return {viewer}.model.materials.map((m) => m.name)")
        assert names == ["bone", "defect template"], names
        assert not driver.find_element(By.ID, "turn-over").is_displayed()
    finally:
        driver.quit()
