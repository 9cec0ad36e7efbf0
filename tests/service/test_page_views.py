"""The page as a person meets it (issue 45), in headless Chromium with a phone's viewport emulated (the window of
headless Chromium is never narrower than 500 px, so a window size alone never tested a phone):

* no horizontal overflow on 360, 390 and 412 px phones and a 1366 x 900 desktop, with every section shown (the
  stack's orientation, the defect, parts and region, a finished job's model, files, share link and the job list):
  the document no wider than the screen, no element past the screen or its card, no button or header broken
  inside a word;
* switching between jobs: every viewer source (``src``, ``ios-src``, ``poster``) is the shown job's, none of a
  failed job;
* each refusal in the page's own words: a dropped .txt, a refused upload (the bar reset), a scan of 2 images (no
  "failed: 1 %"), a scan without its voxel size (the Voxel size field, not the API's ``"spacing"``);
* the page's security headers, no inline script, values from the API as text, and the 3D view under the CSP.

Screenshots of each viewport are kept under pytest's temporary folder (``.../artefacts/``, paths printed).
"""

from __future__ import annotations

import base64
import json
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.service.browser import start_chromium
from tests.service.conftest import HEADSQ, slice_zip, sphere_volume
from tests.service.procs import ServiceStack, wait_for_job, wait_until

STATIC = Path(__file__).resolve().parents[2] / "service" / "static"
VIEWPORTS = [(360, 780), (390, 844), (412, 915), (1366, 900)]
LONG_NAME = "CT_head_neck_with_contrast_export_from_the_hospital_PACS_2026-11-28_series_0004_axial.zip"
# every element past the screen or past its card's content box, and every word broken inside (buttons, headers,
# file names): what a person sees as "the page is wider than my phone" or "Downloa/d"
OVERFLOW_JS = r"""
const vw = document.documentElement.clientWidth, out = [], broken = [];
for (const el of document.querySelectorAll('body *')) {
  if (el.closest('model-viewer') && el.tagName !== 'MODEL-VIEWER') continue; // hotspots float over the 3D view
  const r = el.getBoundingClientRect();
  if (!r.width || !el.getClientRects().length || getComputedStyle(el).visibility === 'hidden') continue;
  const card = el.closest('.card');
  let limit = vw;
  if (card && card !== el) {
    const c = card.getBoundingClientRect(), s = getComputedStyle(card);
    limit = Math.min(vw, c.right - parseFloat(s.paddingRight) - parseFloat(s.borderRightWidth));
  }
  if (r.right > limit + 0.5 || r.left < -0.5) {
    const name = `${el.tagName.toLowerCase()}#${el.id}.${el.className}`;
    out.push(`${name} [${r.left.toFixed(0)}, ${r.right.toFixed(0)}] > ${limit.toFixed(0)}`);
  }
}
for (const el of document.querySelectorAll('button, a.button, th, h1, h2, legend, #facts td:first-child')) {
  if (!el.getClientRects().length) continue;
  const walker = document.createTreeWalker(el, NodeFilter.SHOW_TEXT);
  for (let node = walker.nextNode(); node; node = walker.nextNode()) {
    for (const m of node.data.matchAll(/\S+/g)) {
      const range = document.createRange();
      range.setStart(node, m.index); range.setEnd(node, m.index + m[0].length);
      const tops = new Set([...range.getClientRects()].filter((q) => q.width > 0).map((q) => Math.round(q.top)));
      if (tops.size > 1) broken.push(`${el.tagName.toLowerCase()}#${el.id}: "${m[0]}"`);
    }
  }
}
return {scrollWidth: document.documentElement.scrollWidth, innerWidth: innerWidth, clientWidth: vw,
        outside: out.slice(0, 20), broken: broken.slice(0, 20)};
"""
CSP_WATCH = (
    "window.__csp = []; document.addEventListener('securitypolicyviolation', "
    "(e) => window.__csp.push(`${e.violatedDirective} ${e.blockedURI}`));"
)

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def jobs(stack: ServiceStack) -> dict[str, dict[str, Any]]:
    """Finished jobs of key-a: ``head`` (the bundled CT), ``ball`` (a long upload name, another model) and
    ``two`` (a zip of 2 images: failed)."""
    uploads = {
        "head": (HEADSQ.path.name, HEADSQ.path.read_bytes(), HEADSQ.params),
        "ball": (LONG_NAME, slice_zip(sphere_volume((16, 24, 24), 0.3)), {"spacing": [1, 1, 1], "iso": 500}),
        "two": ("two.zip", slice_zip(sphere_volume((2, 24, 24))), {"spacing": [1, 1, 1]}),
    }
    out = {}
    with stack.client("key-a") as client:
        for name, (filename, data, params) in uploads.items():
            resp = client.post("/v1/jobs", files={"file": (filename, data)}, data={"params": json.dumps(params)})
            assert resp.status_code == 202, resp.text
            out[name] = resp.json()["id"]
        done = {name: wait_for_job(client, job_id, stack=stack, timeout=300) for name, job_id in out.items()}
    assert done["head"]["state"] == done["ball"]["state"] == "succeeded", done
    assert done["two"]["state"] == "failed", done["two"]
    return done


@pytest.fixture
def browser(chromium_paths: tuple[str, str], tmp_path: Path) -> Iterator[Any]:
    driver = start_chromium(*chromium_paths, tmp_path)
    driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": CSP_WATCH})
    try:
        yield driver
    finally:
        driver.quit()


def _js(driver: Any, script: str, *args: Any) -> Any:
    return driver.execute_script(script, *args)


def _viewport(driver: Any, width: int, height: int) -> None:
    """A phone's screen (mobile viewport: the page's meta viewport applies) or a desktop window."""
    driver.execute_cdp_cmd(
        "Emulation.setDeviceMetricsOverride",
        {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": width < 1000},
    )


def _open(driver: Any, base_url: str, key: str = "key-a") -> None:
    from selenium.webdriver.common.by import By

    driver.get(base_url + "/")
    driver.find_element(By.ID, "api-key").send_keys(key)
    driver.find_element(By.ID, "key-save").click()


def _follow(driver: Any, job_id: str) -> None:
    """Open a job from the Recent jobs list, as a person does."""
    wait_until(lambda: _js(driver, f"return !!document.querySelector('#jobs li[data-job=\"{job_id}\"]')"), 30, "list")
    _js(driver, f"document.querySelector('#jobs li[data-job=\"{job_id}\"]').click()")


def _viewer_loaded(driver: Any) -> None:
    wait_until(lambda: _js(driver, "return !document.getElementById('result-box').hidden"), 60, "the result")
    _js(driver, "document.getElementById('viewer').scrollIntoView({block: 'center'})")  # it loads once in view
    wait_until(lambda: _js(driver, "return document.getElementById('viewer').dataset.loaded"), 120, "the model")
    assert _js(driver, "return document.getElementById('viewer').dataset.loaded") == "yes"


def _file_of(url: str | None) -> tuple[str, str] | None:
    """(job id, file name) of a signed /v1/files/ link (its token: base64url of 'job/name/expiry', a signature)."""
    if not url:
        return None
    token = url.rsplit("/", 1)[-1].split(".")[0]
    job, name, _ = base64.urlsafe_b64decode(token + "=" * (-len(token) % 4)).decode().split("/")
    return job, name


def _sources(driver: Any) -> dict[str, tuple[str, str] | None]:
    got = _js(
        driver,
        "const v = document.getElementById('viewer');"
        "return Object.fromEntries(['src', 'ios-src', 'poster'].map((a) => [a, v.getAttribute(a)]));",
    )
    return {name: _file_of(url) for name, url in got.items()}


def _severe(driver: Any) -> list[str]:
    return [str(e) for e in driver.get_log("browser") if e.get("level") == "SEVERE"]


@pytest.mark.parametrize(("width", "height"), VIEWPORTS, ids=[f"{w}x{h}" for w, h in VIEWPORTS])
def test_no_horizontal_overflow_with_every_section_open(
    stack: ServiceStack, jobs: dict[str, dict[str, Any]], browser: Any, artefacts: Path, width: int, height: int
) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    driver = browser
    _viewport(driver, width, height)
    _open(driver, stack.base_url)
    assert _js(driver, "return innerWidth") == width  # the emulated screen, not a 500 px minimum window
    # every section of the form shown and filled: orientation, defect, parts and region, the voxel size
    driver.find_element(By.ID, "defect").click()
    _js(driver, "document.getElementById('first-slice').value = 'inferior'")
    driver.find_element(By.ID, "flip-lr").click()
    driver.find_element(By.ID, "pieces").send_keys("12")
    roi = driver.find_element(By.ID, "roi")
    assert "z, y, x voxel" in roi.get_attribute("placeholder")
    roi.send_keys("0:60, 0:256, 0:256")
    Select(driver.find_element(By.ID, "roi-units")).select_by_value("mm")  # the example follows the units' order
    assert "x, y, z mm" in roi.get_attribute("placeholder")
    driver.find_element(By.ID, "spacing").send_keys("1.5, 0.957, 0.957")
    # a finished job: its model, warnings, placement, files, QR code and share link; the list with a long name
    _follow(driver, jobs["head"]["id"])
    _viewer_loaded(driver)
    wait_until(lambda: driver.find_element(By.CSS_SELECTOR, "#qr svg"), 10, "the QR code")
    wait_until(lambda: driver.find_element(By.ID, "place-box").is_displayed(), 10, "the placement")
    wait_until(lambda: LONG_NAME in driver.find_element(By.ID, "jobs").text, 10, "the long upload name")
    found = _js(driver, OVERFLOW_JS)
    # the whole page, for a person to look at
    full = _js(driver, "return document.documentElement.scrollHeight")
    _viewport(driver, width, min(full, 8000))
    time.sleep(0.5)
    shot = artefacts / f"page-{width}.png"
    driver.save_screenshot(str(shot))
    print(f"\n{width} px: {found['scrollWidth']} px wide; screenshot {shot}")  # noqa: T201
    assert found["scrollWidth"] <= width, found
    assert not found["outside"], found
    assert not found["broken"], found
    # a failed job and a refusal in red: no wider either
    _viewport(driver, width, height)
    _follow(driver, jobs["two"]["id"])
    wait_until(lambda: driver.find_element(By.ID, "job-error").is_displayed(), 30, "the failure")
    found = _js(driver, OVERFLOW_JS)
    assert found["scrollWidth"] <= width and not found["outside"] and not found["broken"], found
    assert not _js(driver, "return window.__csp"), _js(driver, "return window.__csp")
    assert not _severe(driver), _severe(driver)


def test_switching_jobs_changes_every_viewer_source(
    stack: ServiceStack, jobs: dict[str, dict[str, Any]], browser: Any
) -> None:
    """A then B then a failed job then A: ``src`` (phone.glb), ``ios-src`` (model.usdz) and ``poster``
    (preview.png) are always the shown job's; a failed job leaves none (AR Quick Look never gets another job's
    model), and neither do the files, the QR code or the share link."""
    from selenium.webdriver.common.by import By

    driver = browser
    _open(driver, stack.base_url)
    head, ball, two = (jobs[k]["id"] for k in ("head", "ball", "two"))
    for job_id in (head, ball, two, head, ball):
        _follow(driver, job_id)
        wait_until(lambda: driver.find_element(By.ID, "job-id").text == job_id, 10, "the job")  # noqa: B023
        if job_id == two:
            wait_until(lambda: driver.find_element(By.ID, "job-box").get_attribute("data-state") == "failed", 30, "")
            assert _sources(driver) == {"src": None, "ios-src": None, "poster": None}
            assert not driver.find_element(By.ID, "result-box").is_displayed()
            assert not _js(driver, "return document.querySelectorAll('#facts tbody tr, #qr svg').length")
            assert _js(driver, "return document.getElementById('share-url').value") == ""
            continue
        wait_until(lambda: driver.find_element(By.ID, "result-box").is_displayed(), 30, "the result")
        assert _sources(driver) == {
            "src": (job_id, "phone.glb"),
            "ios-src": (job_id, "model.usdz"),
            "poster": (job_id, "preview.png"),
        }
        links = _js(driver, "return [...document.querySelectorAll('#facts a.download')].map((a) => a.href)")
        assert links and {_file_of(u)[0] for u in links} == {job_id}  # type: ignore[index]
        assert _file_of(_js(driver, "return document.getElementById('share-url').value")) == (job_id, "phone.glb")
        _viewer_loaded(driver)
        # Android's AR button swaps src to ar.glb: of this job too
        _js(
            driver,
            "Object.defineProperty(navigator, 'userAgent', {get: () => 'Mozilla/5.0 (Linux; Android 14)',"
            " configurable: true}); document.getElementById('ar-button').click()",
        )
        assert _sources(driver)["src"] == (job_id, "ar.glb")


def test_refusals_in_the_pages_words(
    stack: ServiceStack, jobs: dict[str, dict[str, Any]], browser: Any, tmp_path: Path
) -> None:
    """A .txt dropped on the page is refused naming it; a refused upload empties the bar and says why in red;
    a zip of 2 images fails saying so, without "failed: 1 %"; a scan without its voxel size points at the Voxel
    size field (never the API's ``"spacing"`` in params)."""
    from selenium.webdriver.common.by import By

    driver = browser
    _viewport(driver, 390, 844)
    _open(driver, stack.base_url)
    picked = driver.find_element(By.ID, "picked")

    # a .txt dropped anywhere on the page (not only on the drop zone): refused under its own name, in red
    _js(
        driver,
        "const dt = new DataTransfer(); dt.items.add(new File(['not a scan'], 'notes.txt', {type: 'text/plain'}));"
        "document.querySelector('header').dispatchEvent(new DragEvent('drop', {dataTransfer: dt, bubbles: true,"
        " cancelable: true}));",
    )
    wait_until(lambda: "notes.txt" in picked.text, 10, "the .txt refusal")
    assert "not slice images or DICOM files" in picked.text and picked.get_attribute("class") == "error"
    assert driver.current_url.rstrip("/") == stack.base_url  # the browser did not open the file instead
    driver.find_element(By.ID, "start").click()  # nothing chosen: said, no alert
    assert driver.find_element(By.ID, "upload-text").text.startswith("Choose a scan first")

    file_input = driver.find_element(By.ID, "file-input")
    _js(driver, "arguments[0].hidden = false", file_input)
    bar = "document.getElementById('upload-bar')"

    # not an archive: 415 from the API; the bar empty and hidden, the reason in red
    noise = tmp_path / "noise.zip"
    noise.write_bytes(b"\x00not a zip at all\x01" * 4096)
    file_input.send_keys(str(noise))
    wait_until(lambda: "noise.zip" in picked.text, 10, "the file to be picked")
    assert picked.get_attribute("class") == "muted"  # the .txt refusal is gone
    driver.find_element(By.ID, "spacing").send_keys("1, 1, 1")
    driver.find_element(By.ID, "start").click()
    text = lambda: driver.find_element(By.ID, "upload-text").text  # noqa: E731
    wait_until(lambda: text().startswith("refused:"), 60, "the refusal")
    assert _js(driver, f"return {bar}.value") == 0 and not driver.find_element(By.ID, "upload-bar").is_displayed()
    assert driver.find_element(By.ID, "upload-text").value_of_css_property("color") == "rgba(170, 0, 0, 1)"
    assert not driver.find_element(By.ID, "start").get_attribute("disabled")

    # a scan without its voxel size: the page's words, the field marked and focused
    driver.find_element(By.ID, "spacing").clear()
    nospacing = tmp_path / "ball.zip"
    nospacing.write_bytes(slice_zip(sphere_volume((16, 24, 24), 0.3)))
    file_input.clear()
    file_input.send_keys(str(nospacing))
    wait_until(lambda: "ball.zip" in picked.text, 10, "the file to be picked")
    driver.find_element(By.ID, "start").click()
    wait_until(lambda: text().startswith("refused:"), 60, "the refusal")
    assert "Voxel size field" in text() and '"spacing"' not in text() and "params" not in text(), text()
    assert _js(driver, "return document.activeElement.id") == "spacing"
    assert "needed" in driver.find_element(By.ID, "spacing").get_attribute("class")
    assert _js(driver, f"return {bar}.value") == 0
    # the same words when a job fails with no_spacing (the worker's message names params too)
    words = _js(driver, "return failureText({code: 'no_spacing', message: 'x: send \"spacing\" in params'})")
    assert "Voxel size field" in words and "params" not in words, words

    # a zip of 2 images: the job fails; its state says failed (no percentage) and the message says why
    _follow(driver, jobs["two"]["id"])
    wait_until(lambda: driver.find_element(By.ID, "job-box").get_attribute("data-state") == "failed", 30, "failed")
    state = driver.find_element(By.ID, "job-state").text
    assert state.startswith("failed") and "%" not in state, state
    assert not driver.find_element(By.ID, "job-bar").is_displayed()
    error = driver.find_element(By.ID, "job-error").text
    assert error.startswith("It did not work: ") and "2 image" in error and "at least 3" in error, error
    assert not error.endswith(".."), error


def test_values_from_the_api_are_text(stack: ServiceStack, jobs: dict[str, dict[str, Any]], browser: Any) -> None:
    """``labels/<name>.stl`` and an upload named like markup are shown as written: the page builds its rows and
    list with text nodes, and no script of the page writes HTML."""
    from selenium.webdriver.common.by import By

    source = (STATIC / "page.js").read_text()
    assert not re.search(r"\.(innerHTML|outerHTML)\b|insertAdjacentHTML|document\.write", source)
    driver = browser
    _open(driver, stack.base_url)
    _follow(driver, jobs["head"]["id"])
    wait_until(lambda: driver.find_element(By.ID, "result-box").is_displayed(), 30, "the result")
    row = _js(
        driver,
        "const tr = fileRow({name: 'labels.zip', kind: 'labels', purpose: 'labels/<name>.stl, one per label',"
        " triangles: null, bytes: 1234, url: '/x'}); return [...tr.cells].map((c) => c.textContent);",
    )
    assert row[:2] == ["labels.zip", "labels/<name>.stl, one per label"], row
    li = _js(
        driver,
        "const li = jobRow({id: 'j1', upload_name: '<img src=x onerror=alert(1)>.zip', state: 'failed',"
        " created_at: '2026-11-28T10:00:00Z', outputs: []});"
        "return [li.textContent, li.querySelectorAll('img').length];",
    )
    assert li[0].startswith("<img src=x onerror=alert(1)>.zip · failed") and li[1] == 0, li


def test_security_headers_and_no_inline_script(stack: ServiceStack) -> None:
    """The page: a CSP without inline script or eval (WebAssembly allowed: the Draco and meshopt decoders), no
    framing, nosniff, no Referer; the HTML holds no inline script and no event-handler attribute."""
    page = httpx.get(stack.base_url + "/")
    assert page.status_code == 200
    csp = {d.split()[0]: d.split()[1:] for d in page.headers["content-security-policy"].split(";") if d.strip()}
    assert csp["default-src"] == ["'none'"] and csp["frame-ancestors"] == ["'none'"]
    assert "'unsafe-inline'" not in csp["script-src"] and "'unsafe-eval'" not in csp["script-src"]
    assert csp["script-src"] == ["'self'", "'wasm-unsafe-eval'"] and csp["object-src"] == ["'none'"]
    assert page.headers["x-content-type-options"] == "nosniff"
    assert page.headers["referrer-policy"] == "no-referrer"
    assert page.headers["x-frame-options"] == "DENY"
    html = page.text
    assert not re.search(r"<script(?![^>]*\bsrc=)[^>]*>", html), "an inline script"
    assert not re.search(r"\son[a-z]+\s*=", html), "an inline event handler"
    assert "//" not in "".join(re.findall(r'src="([^"]*)"', html)), "a script from elsewhere"
    for path in ("/static/page.js", "/v1/jobs", "/healthz"):
        assert httpx.get(stack.base_url + path).headers["x-content-type-options"] == "nosniff"


def test_security_headers_name_the_store_for_direct_uploads(tmp_path: Path) -> None:
    """With S3 storage the page's CSP lets it reach the store (direct uploads, store download links)."""
    from core.settings import Settings
    from service.app import page_csp

    settings = Settings(
        data_dir=tmp_path, storage_url="s3://bucket/prefix", s3_endpoint_url="http://store.example:8333/"
    )
    csp = page_csp(settings)
    assert "connect-src 'self' blob: data: http://store.example:8333;" in csp
    assert "img-src 'self' blob: data: http://store.example:8333;" in csp
    assert "store.example" not in page_csp(Settings(data_dir=tmp_path))
