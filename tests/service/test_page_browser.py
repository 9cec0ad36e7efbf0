"""The page in a real browser (headless Chromium): enter the key, choose the bundled scan, upload, watch the job,
see the model in 3D, download a file; everything the page loads comes from the service itself.

The screenshots are kept as test artefacts (their paths are printed): ``page.png`` (the whole page) and
``viewer.png`` (the 3D view).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from engine.export.files import FILES
from tests.service.browser import start_chromium
from tests.service.conftest import HEADSQ
from tests.service.procs import ServiceStack, wait_for_job, wait_until

pytestmark = pytest.mark.browser


def _js(driver: Any, script: str, *args: Any) -> Any:
    return driver.execute_script(script, *args)


def test_upload_watch_view_download(
    stack: ServiceStack, chromium_paths: tuple[str, str], artefacts: Path, tmp_path: Path
) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    downloads = tmp_path / "downloads"
    downloads.mkdir()
    driver = start_chromium(*chromium_paths, downloads)
    # every Content-Security-Policy violation of the page, from its first byte on
    driver.execute_cdp_cmd(
        "Page.addScriptToEvaluateOnNewDocument",
        {
            "source": "window.__csp = []; document.addEventListener('securitypolicyviolation',"
            " (e) => window.__csp.push(`${e.violatedDirective} ${e.blockedURI}`));"
        },
    )
    try:
        assert (
            "script-src 'self' 'wasm-unsafe-eval'" in httpx.get(stack.base_url + "/").headers["content-security-policy"]
        )
        driver.get(stack.base_url + "/")
        assert "bonemesh" in driver.title
        assert not driver.find_elements(By.ID, "assets-missing"), "the service found no node_modules"
        driver.find_element(By.ID, "api-key").send_keys("key-a")
        driver.find_element(By.ID, "key-save").click()
        assert _js(driver, "return sessionStorage.getItem('bonemesh-api-key')") == "key-a"  # this tab only
        assert _js(driver, "return localStorage.getItem('bonemesh-api-key')") is None  # not on the device unasked
        assert "key-a" not in driver.current_url
        file_input = driver.find_element(By.ID, "file-input")
        _js(driver, "arguments[0].hidden = false", file_input)
        file_input.send_keys(str(HEADSQ.path))
        wait_until(lambda: "headsq" in driver.find_element(By.ID, "picked").text, 10, "the file to be picked")
        Select(driver.find_element(By.ID, "level-kind")).select_by_value("iso")
        driver.find_element(By.ID, "iso").send_keys(str(HEADSQ.params["iso"]))
        driver.find_element(By.ID, "spacing").send_keys(", ".join(str(v) for v in HEADSQ.params["spacing"]))
        driver.find_element(By.ID, "start").click()

        # upload progress, then the job's stages and percentages as the page shows them
        wait_until(lambda: driver.find_element(By.ID, "upload-text").text == "uploaded", 60, "the upload")
        seen: list[str] = []
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            state = driver.find_element(By.ID, "job-box").get_attribute("data-state") or ""
            text = driver.find_element(By.ID, "job-state").text
            if text and (not seen or seen[-1] != text):
                seen.append(text)
            if state in ("succeeded", "failed", "cancelled"):
                break
            time.sleep(0.05)  # faster than the page asks a young job (every 0.25 s)
        assert state == "succeeded", f"{state}: {seen} {driver.find_element(By.ID, 'job-error').text}"
        assert any("running" in s for s in seen), seen  # the live stage was shown before the end
        assert seen[-1] == "succeeded: 100 %", seen

        # the 3D view: the Draco phone model loaded (decoder from this server) and visible
        wait_until(lambda: _js(driver, "return document.getElementById('viewer').dataset.loaded"), 120, "the model")
        assert _js(driver, "return document.getElementById('viewer').dataset.loaded") == "yes", _console(driver)
        wait_until(lambda: _js(driver, "return document.getElementById('viewer').modelIsVisible"), 60, "the render")
        dims = _js(driver, "const d = document.getElementById('viewer').getDimensions(); return [d.x, d.y, d.z]")
        assert 0.05 < max(dims) < 0.5, dims  # metres: a head, not millimetres
        time.sleep(1.5)  # the first frames fade the model in
        viewer = driver.find_element(By.ID, "viewer")
        _js(driver, "arguments[0].scrollIntoView({block: 'center'})", viewer)
        viewer_png, page_png = artefacts / "viewer.png", artefacts / "page.png"
        viewer.screenshot(str(viewer_png))
        driver.save_screenshot(str(page_png))
        print(f"\nscreenshots: {viewer_png} {page_png}")  # noqa: T201
        _assert_model_framed(viewer_png)

        # every output has a download button; one download arrives whole
        rows = driver.find_elements(By.CSS_SELECTOR, "#facts a.download")
        names = {a.get_attribute("data-name") for a in rows}
        assert {"model.stl", "phone.glb", "ar.glb", "model.usdz", "phone_meshopt.glb", "preview.png"} <= names
        # each file's "for" column is the registry's purpose, as the job resource carries it
        cells = _js(
            driver,
            "return [...document.querySelectorAll('#facts tbody tr')]"
            ".map(r => [r.cells[0].textContent, r.cells[1].textContent])",
        )
        assert cells and all(FILES[name].purpose == shown for name, shown in cells), cells
        link = next(a for a in rows if a.get_attribute("data-name") == "phone.glb")
        with stack.client(None) as anon:
            expected = int(anon.head(link.get_attribute("href")).headers["content-length"])
        link.click()
        wait_until(lambda: (downloads / "phone.glb").is_file(), 30, "the download")
        wait_until(lambda: (downloads / "phone.glb").stat().st_size == expected, 10, "the whole download")
        assert (downloads / "phone.glb").read_bytes()[:4] == b"glTF"
        assert driver.find_element(By.CSS_SELECTOR, "#qr svg"), "no QR code for the phone link"

        # the recent jobs list, with the thumbnail
        wait_until(
            lambda: _js(driver, "return [...document.querySelectorAll('#jobs img')].some(i => i.naturalWidth > 0)"),
            30,
            "a job thumbnail in the list",
        )
        # nothing came from elsewhere: every resource the page loaded is the service's
        urls = _js(driver, "return performance.getEntriesByType('resource').map(e => e.name)")
        assert urls and all(u.startswith(stack.base_url) or u.startswith(("blob:", "data:")) for u in urls), urls
        assert any("/vendor/draco/" in u for u in urls), urls  # the Draco decoder was served here
        # ... and it ran under the page's CSP (WebAssembly compiled, its blob: worker started): nothing was blocked
        assert _js(driver, "return window.__csp") == [], _js(driver, "return window.__csp")
    finally:
        driver.quit()


def _console(driver: Any) -> str:
    try:
        return "\n".join(str(e) for e in driver.get_log("browser"))[-3000:]
    except Exception:  # not every driver keeps the log
        return ""


def _assert_model_framed(path: Path) -> None:
    """The screenshot shows the model: pixels that differ from the background gradient, inside the frame."""
    import imageio.v3 as iio

    image = iio.imread(path)[12:-12, 12:-12, :3].astype(float)  # inside the rounded corners
    background = np.median(image[:, :8], axis=1)  # the left border, row by row (vertical gradient)
    diff = np.abs(image - background[:, None, :]).sum(axis=2) > 40
    rows, cols = np.nonzero(diff)
    assert diff.mean() > 0.03, f"the model is not visible in {path} ({diff.mean():.3f} of the pixels)"
    h, w = diff.shape
    assert rows.min() > 0.02 * h and rows.max() < 0.98 * h, f"the model touches the top or bottom in {path}"
    assert cols.min() > 0.02 * w and cols.max() < 0.98 * w, f"the model touches the sides in {path}"


def _severe(driver: Any) -> list[str]:
    return [str(e) for e in driver.get_log("browser") if e.get("level") == "SEVERE"]


def _no_overflow(driver: Any, width: int) -> None:
    widths = _js(driver, "return [document.documentElement.scrollWidth, window.innerWidth]")
    assert widths[0] <= width and widths[1] == width, f"the page is {widths[0]} px wide on a {width} px screen"


@pytest.mark.parametrize("width", [412, 1366])
def test_phone_and_desktop_orient_ar_and_messages(
    stack: ServiceStack, chromium_paths: tuple[str, str], tmp_path: Path, width: int
) -> None:
    """Issue 27: orientation before upload and after (placed again: absolute choices, the one already published
    sends nothing), direction labels, no horizontal overflow (on an emulated phone screen: headless Chromium's
    window is never narrower than 500 px), the AR file for Android, progress in view, the voxel size's own error,
    a refused .txt under its own name, a dark backdrop, and no console error (the favicon)."""
    from selenium.webdriver.common.by import By

    from tests.service.conftest import slice_zip, sphere_volume

    vol = sphere_volume((16, 24, 24), 0.3)
    vol[1:4, 10:14, 10:14] = 1000
    scan = tmp_path / "marked.zip"
    scan.write_bytes(slice_zip(vol))
    notes = tmp_path / "notes.txt"
    notes.write_text("not a scan")
    readme = tmp_path / "readme.txt"
    readme.write_text("nor this")
    driver = start_chromium(*chromium_paths, tmp_path, width=width, height=860)
    try:
        driver.execute_cdp_cmd(
            "Emulation.setDeviceMetricsOverride",
            {"width": width, "height": 860, "deviceScaleFactor": 1, "mobile": width < 1000},
        )
        driver.get(stack.base_url + "/")
        driver.find_element(By.ID, "api-key").send_keys("key-a")
        driver.find_element(By.ID, "key-save").click()
        file_input = driver.find_element(By.ID, "file-input")
        _js(driver, "arguments[0].hidden = false", file_input)
        file_input.send_keys(f"{notes}\n{readme}")  # two files: once zipped and called 'slices.zip'
        wait_until(lambda: "notes.txt" in driver.find_element(By.ID, "picked").text, 10, "the refusal")
        assert "slices.zip" not in driver.find_element(By.ID, "picked").text
        file_input.clear()
        file_input.send_keys(str(scan))
        wait_until(lambda: "marked.zip" in driver.find_element(By.ID, "picked").text, 10, "the file to be picked")
        _js(driver, "document.getElementById('level-kind').value = 'iso'")
        driver.find_element(By.ID, "iso").send_keys("500")
        spacing = driver.find_element(By.ID, "spacing")
        spacing.send_keys("1.5, 0.957")  # two numbers: refused, naming the field
        driver.find_element(By.ID, "start").click()
        message = driver.find_element(By.ID, "upload-text").text
        assert message.startswith("Voxel size") and "spacing" not in message, message
        spacing.clear()
        spacing.send_keys("1, 1, 2")  # z = y != x: looks like an x, y, z size; the job runs and the page says so
        _js(driver, "document.getElementById('first-slice').value = 'inferior'")
        driver.find_element(By.ID, "flip-ap").click()
        driver.find_element(By.ID, "start").click()
        wait_until(lambda: driver.find_element(By.ID, "job-box").is_displayed(), 30, "the job box")
        time.sleep(0.3)
        top, bottom = _js(
            driver, "const r = document.getElementById('job-box').getBoundingClientRect(); return [r.top, r.bottom]"
        )
        assert 0 <= top < _js(driver, "return innerHeight"), (top, bottom)  # the progress is in view
        wait_until(lambda: driver.find_element(By.ID, "job-box").get_attribute("data-state") == "succeeded", 120, "job")
        job_id = driver.find_element(By.ID, "job-id").text
        with stack.client("key-a") as client:
            job = client.get(f"/v1/jobs/{job_id}").json()
        assert job["params"]["orient"] == {"first_slice": "inferior", "flip_lr": False, "flip_ap": True}
        _js(driver, "document.getElementById('viewer').scrollIntoView()")  # model-viewer loads once in view
        wait_until(lambda: _js(driver, "return document.getElementById('viewer').dataset.loaded"), 60, "the view")
        assert _js(driver, "return document.getElementById('viewer').dataset.loaded") == "yes", _console(driver)
        _no_overflow(driver, width)
        # what the report doubts is shown beside the model (here: the voxel size's order)
        wait_until(lambda: driver.find_element(By.ID, "model-warnings").is_displayed(), 10, "the model's warnings")
        codes = _js(driver, "return [...document.querySelectorAll('#model-warnings li')].map(li => li.dataset.code)")
        assert codes == ["voxel_size_order"], codes
        # the directions beside the model: S above it (+Y), A toward the viewer (+Z)
        spots = _js(
            driver,
            "return Object.fromEntries([...document.querySelectorAll('#viewer .dir')]"
            ".map(e => [e.dataset.dir, e.dataset.position || '']))",
        )
        assert float(spots["S"].split()[1]) > 0 and float(spots["A"].split()[2]) > 0, spots
        # a dark backdrop: the pale model stands out
        background = _js(driver, "return getComputedStyle(document.getElementById('viewer')).backgroundImage")
        assert "linear-gradient" in background and "rgb(253, 253, 253)" not in background, background
        # Android: Scene Viewer gets ar.glb (model-viewer hands it its src)
        ar_url = next(o["url"] for o in job["outputs"] if o["name"] == "ar.glb")
        phone_url = next(o["url"] for o in job["outputs"] if o["name"] == "phone.glb")
        assert (
            _js(driver, "return document.getElementById('viewer').getAttribute('src')").split("/")[-1][:20]
            == (phone_url.split("/")[-1][:20])
        )
        _js(
            driver,
            "Object.defineProperty(navigator, 'userAgent', {get: () => 'Mozilla/5.0 (Linux; Android 14)'});"
            "document.getElementById('ar-button').click()",
        )
        src = _js(driver, "return document.getElementById('viewer').getAttribute('src')")
        assert src.split("/")[-1][:20] == ar_url.split("/")[-1][:20], (src, ar_url)
        # placed again: the published orientation is checked, choosing it again sends nothing; the head end on the
        # first slice and the front on the top of the images (the default convention) re-publish every output
        before = json.loads(httpx.get(next(o["url"] for o in job["outputs"] if o["name"] == "report.json")).text)
        apply = driver.find_element(By.ID, "place-apply")
        wait_until(lambda: driver.find_element(By.ID, "place-box").is_displayed(), 30, "the placement")
        checked = "return [...document.querySelectorAll('#place-box input:checked')].map((r) => r.value)"
        assert _js(driver, checked) == ["inferior", "posterior", "right"]
        assert not apply.is_enabled() and apply.text == "Placed so"
        assert "the last slice" in driver.find_element(By.ID, "orient-state").text
        driver.find_element(By.CSS_SELECTOR, "input[name=place-first][value=inferior]").click()  # the same again
        assert not apply.is_enabled()
        driver.find_element(By.CSS_SELECTOR, "input[name=place-first][value=superior]").click()
        driver.find_element(By.CSS_SELECTOR, "input[name=place-ap][value=anterior]").click()
        assert apply.is_enabled() and apply.text == "Place it so"
        apply.click()
        with stack.client("key-a") as client:
            job = wait_for_job(
                client,
                job_id,
                timeout=60,
                until=lambda j: j["stage"] == "done" and j["params"]["orient"]["first_slice"] == "superior",
            )
        after = json.loads(httpx.get(next(o["url"] for o in job["outputs"] if o["name"] == "report.json")).text)
        assert after["frame"]["patient_from_grid_xyz"] != before["frame"]["patient_from_grid_xyz"]
        assert after["parameters"]["orient"] == {"first_slice": "superior", "flip_lr": False, "flip_ap": False}
        wait_until(lambda: "first slice superior" in driver.find_element(By.ID, "frame-text").text, 30, "new frame")
        wait_until(lambda: _js(driver, checked) == ["superior", "anterior", "right"], 30, "the new placement")
        assert not apply.is_enabled()  # placed so: pressing again would change nothing
        _no_overflow(driver, width)
        assert not _severe(driver), _severe(driver)
    finally:
        driver.quit()
