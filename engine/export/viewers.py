"""The files made from the viewing copies (the phone and AR meshes): the phone app's Draco GLB, the plain AR GLB,
a meshopt GLB (three.js, model-viewer without Draco's WASM), a USDZ for iOS AR Quick Look and a PNG thumbnail for
lists. Which files they are, from which copy and by which exporter is the registry's
(``engine.export.files.viewing_files``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

from engine.export.files import Exporter, exporter_of, viewing_files


def small_files(
    phone: Any, ar: Any, parts: Mapping[str, Sequence[Any]] | None = None, device: Any = None
) -> dict[str, Callable[[], bytes]]:
    """Every small file of a model as a function that encodes it, from meshes with ``vertices``, ``faces`` and
    ``normals`` (engine order, mm; centred as the glTF files are), in the registry's order: ``phone.glb``,
    ``ar.glb``, ``phone_meshopt.glb``, ``model.usdz``, ``preview.png`` (``engine.job.outputs`` runs them one after
    another). ``parts``: named parts beside each copy (``{"phone": [Part, ...], "ar": [...]}``, e.g. the defect
    template), given to the files whose exporter takes them (``OutputFile.parts``). The exporters are looked up
    when this is called. ``device``: where the files whose exporter runs device kernels (``OutputFile.device``: the
    preview's rasteriser) run them (a backend, a spec or a Warp device: the job's; None: Warp's current device)."""
    meshes: dict[str | None, Any] = {"phone": phone, "ar": ar}
    beside = parts or {}
    return {
        f.name: _encoder(
            exporter_of(f),
            meshes[f.made_from],
            beside.get(str(f.made_from), ()) if f.parts else (),
            {"device": device} if f.device and device is not None else {},
        )
        for f in viewing_files()
    }


def _encoder(export: Exporter, mesh: Any, parts: Sequence[Any], options: dict[str, Any]) -> Callable[[], bytes]:
    if parts:
        return lambda: export(mesh.vertices, mesh.faces, mesh.normals, parts=parts, **options)
    return lambda: export(mesh.vertices, mesh.faces, mesh.normals, **options)
