"""The files for viewers beyond the phone app's Draco GLB, made from the phone and AR meshes: a meshopt GLB
(three.js, model-viewer without Draco's WASM), a USDZ for iOS AR Quick Look, and a PNG thumbnail for lists."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from engine.export.meshopt import to_meshopt_glb
from engine.export.preview import to_preview_png
from engine.export.usdz import to_usdz


def small_files(phone: Any, ar: Any) -> dict[str, Callable[[], bytes]]:
    """Every small file of a model as a function that encodes it, from meshes with ``vertices``, ``faces`` and
    ``normals`` (engine order, mm; centred as the glTF files are): the Draco ``phone.glb``, the plain ``ar.glb``,
    the meshopt GLB, the USDZ and the preview (``engine.outputs`` runs them one after another)."""
    from engine.export import to_draco_glb, to_glb

    return {
        "phone.glb": lambda: to_draco_glb(phone.vertices, phone.faces, phone.normals),
        "ar.glb": lambda: to_glb(ar.vertices, ar.faces, ar.normals),
        "phone_meshopt.glb": lambda: to_meshopt_glb(phone.vertices, phone.faces, phone.normals),
        "model.usdz": lambda: to_usdz(ar.vertices, ar.faces, ar.normals),
        "preview.png": lambda: to_preview_png(phone.vertices, phone.faces, phone.normals),
    }
