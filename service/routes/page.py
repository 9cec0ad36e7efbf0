"""The web page at ``/``: upload a scan, watch the job, view the model in 3D, download, share, AR.

The page is this package's ``static/`` folder; its libraries (``<model-viewer>`` with three.js, the Draco and
meshopt decoders, the Basis transcoder, a QR code generator) come from the npm packages pinned in ``package.json``
and installed into ``node_modules`` by the setup script and the Docker build: the service serves them itself, so
the page works without internet. Only the files named in ``VENDOR`` are served from there. Without them the page
still loads and says the viewer assets are missing.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse, HTMLResponse, Response

from core.settings import Settings
from service.deps import SettingsDep
from service.problems import Problem

router = APIRouter(include_in_schema=False)
STATIC = Path(__file__).resolve().parents[1] / "static"
PAGE_FILES = {"page.js": "text/javascript", "page.css": "text/css"}
# what the page loads, by the name it asks for -> the file under node_modules
VENDOR = {
    "model-viewer.min.js": "@google/model-viewer/dist/model-viewer.min.js",
    "qrcode.js": "qrcode-generator/dist/qrcode.js",
    "meshopt_decoder.js": "meshoptimizer/meshopt_decoder.cjs",
    "draco/draco_decoder.js": "three/examples/jsm/libs/draco/gltf/draco_decoder.js",
    "draco/draco_decoder.wasm": "three/examples/jsm/libs/draco/gltf/draco_decoder.wasm",
    "draco/draco_wasm_wrapper.js": "three/examples/jsm/libs/draco/gltf/draco_wasm_wrapper.js",
    "basis/basis_transcoder.js": "three/examples/jsm/libs/basis/basis_transcoder.js",
    "basis/basis_transcoder.wasm": "three/examples/jsm/libs/basis/basis_transcoder.wasm",
}
MEDIA = {".js": "text/javascript", ".wasm": "application/wasm"}
MISSING_BANNER = (
    '<p class="banner" id="assets-missing">The 3D viewer\'s files are missing on this server (no node_modules): '
    "uploads and downloads work, the 3D view does not. Install them with <code>npm ci</code> in the service's "
    "folder (scripts/_setup.sh does).</p>"
)


def assets_dir(settings: Settings) -> Path:
    """Where the npm packages are: ``BONEMESH_ASSETS_DIR``, else ``node_modules`` beside the source tree."""
    return settings.assets_dir or Path(__file__).resolve().parents[2] / "node_modules"


@cache
def _page(missing: bool) -> str:
    html = (STATIC / "index.html").read_text()
    return html.replace("<!--ASSETS-->", MISSING_BANNER if missing else "")


def vendor_missing(settings: Settings) -> list[str]:
    """The viewer files not found (empty when the page is complete)."""
    root = assets_dir(settings)
    return [name for name, rel in VENDOR.items() if not (root / rel).is_file()]


@router.get("/", response_class=HTMLResponse)
def page(settings: SettingsDep) -> HTMLResponse:
    return HTMLResponse(_page(bool(vendor_missing(settings))), headers={"cache-control": "no-cache"})


@router.get("/static/{name}")
def page_file(name: str) -> Response:
    if name not in PAGE_FILES:
        raise Problem(404, f"no page file {name}")
    return FileResponse(STATIC / name, media_type=PAGE_FILES[name], headers={"cache-control": "no-cache"})


@router.get("/vendor/{name:path}")
def vendor_file(name: str, settings: SettingsDep) -> Response:
    rel = VENDOR.get(name)
    path = assets_dir(settings) / rel if rel else None
    if path is None or not path.is_file():
        raise Problem(404, f"the viewer file {name} is not installed on this server (run npm ci)")
    media = MEDIA.get(path.suffix, "text/javascript")  # .cjs: a classic script
    return FileResponse(path, media_type=media, headers={"cache-control": "public, max-age=86400"})
