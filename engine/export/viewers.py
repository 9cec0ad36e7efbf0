"""The files for viewers beyond the phone app's Draco GLB, made from the phone and AR meshes: a meshopt GLB
(three.js, model-viewer without Draco's WASM), a USDZ for iOS AR Quick Look, and a PNG thumbnail for lists."""

from __future__ import annotations

from typing import Any

from engine.export.meshopt import to_meshopt_glb
from engine.export.preview import to_preview_png
from engine.export.usdz import to_usdz

VIEWER_FILES = ("phone_meshopt.glb", "model.usdz", "preview.png")


def viewer_files(phone: Any, ar: Any) -> dict[str, bytes]:
    """``{name: bytes}`` of :data:`VIEWER_FILES`, from meshes with ``vertices``, ``faces`` and ``normals``
    (engine order, mm; centred as the glTF files are)."""
    return {
        "phone_meshopt.glb": to_meshopt_glb(phone.vertices, phone.faces, phone.normals),
        "model.usdz": to_usdz(ar.vertices, ar.faces, ar.normals),
        "preview.png": to_preview_png(phone.vertices, phone.faces, phone.normals),
    }
