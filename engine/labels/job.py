"""A label job of the service, from its upload or its scan (``worker.tasks`` calls ``label_job``): a label map
(``engine.labels.uploads``) or a CT's largest bone ``pieces`` (``engine.labels.pieces.bone_pieces``), cropped to a
region of interest when asked, meshed per label (``label_models``) and written as a label job's files
(``engine.labels.outputs.write_label_outputs``)."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from engine.export.files import REPORT_JSON
from engine.params import PiecesParams, ReconParams, RoiParams

__all__ = ["label_job"]


def label_job(
    source: Any,
    outdir: str | Path,
    params: ReconParams,
    *,
    found: Any = None,
    pieces: PiecesParams | None = None,
    roi: RoiParams | None = None,
    segments: Sequence[int | str] | None = None,
    device: Any = "auto",
    label: str = "the upload",
    on_stage: Callable[[str], None] | None = None,
) -> tuple[dict[str, Path], dict[str, Any]]:
    """Mesh every label and write the files into ``outdir``: ``source`` is the upload's path when ``found`` (a
    ``LabelUpload``) says it holds a label map, else a loaded scan (an ``engine.types.Volume``, cropped already)
    whose ``pieces`` largest bone pieces become the labels; ``roi`` crops a label map before meshing; ``segments``
    keeps only those segments (numbers or names; ``engine.labels.pieces.select_segments``).
    ``on_stage`` is told each stage as it begins (``"labels"``: meshing, ``"writing"``: the files).

    Returns:
        ({file name: path}, the report).

    Raises:
        LabelError, InputError, EmptySurfaceError: bad input, each with a clear message; nothing is written.
    """
    from engine.labels.outputs import write_label_outputs
    from engine.labels.parts import label_models
    from engine.labels.pieces import bone_pieces, crop_roi, select_segments
    from engine.labels.uploads import read_label_upload

    if found is not None:
        lv = read_label_upload(source, found, label)
        if roi is not None:
            lv = crop_roi(lv, roi, params.orient)
    else:
        lv = bone_pieces(source, params, pieces or PiecesParams())
    if segments:
        lv = select_segments(lv, segments)
    stage = on_stage or (lambda name: None)
    stage("labels")
    models = label_models(lv, params, device=device, orient=params.orient)
    stage("writing")
    extra = {
        "input": {
            "shape_zyx": list(lv.labels.shape),
            "spacing_zyx_mm": list(lv.spacing_zyx_mm),
            "origin_lps_mm": list(lv.origin_mm),
            "segments": len(lv.segments),
        }
    }
    paths = write_label_outputs(models, outdir, params, device=device, extra=extra)
    return paths, json.loads(paths[REPORT_JSON].read_text())
