"""What can be refused about an upload before it is queued: not an archive, unsafe names, too many members, a bomb
(by the declared sizes: member and whole-archive ratios, total expanded size), nothing to build from, or an image
stack that certainly needs a voxel size and was sent without one. A label map (NIfTI, NRRD/.seg.nrrd, or a zip of
one or of a DICOM SEG with its CT: ``engine.labels.uploads``) is taken by its content; a float NIfTI, or an upload
without a label map sent with ``"labels": true``, is refused. Loading checks the rest (actual bytes, shapes).
"""

from __future__ import annotations

import zipfile
from pathlib import Path

from core.logsafe import relabel
from core.params import JobParams
from service.uploads import UploadError

# image formats that never carry a voxel size (TIFF tags and DICOM headers may)
NO_SPACING_KINDS = frozenset({"png", "jpeg", "bmp", "npy"})


def inspect_upload(path: Path, filename: str | None, params: JobParams) -> str:
    """A one-line summary of a stored upload (for the log: no names in it).

    Raises:
        UploadError: 415 for what is not a scan container, 422 for an unsafe, oversized or unusable one, or for
            a PNG/JPEG/BMP/.npy stack without ``spacing`` in the params.
    """
    from engine.errors import InputError, NotAScanError
    from engine.io import inspect_input
    from engine.io.archive import open_members
    from engine.io.stack import image_kind

    labels = _label_map(path, filename, params)
    if labels is not None:
        return labels
    try:
        summary = inspect_input(path)
    except NotAScanError as exc:  # not a container bonemesh reads (by type: engine.errors)
        raise UploadError(415, relabel(str(exc), filename)) from None
    except InputError as exc:
        raise UploadError(422, relabel(str(exc), filename)) from None
    if summary.dicom == 0 and params.spacing is None:
        with open_members(path, heads_only=True) as members:
            kinds = {image_kind(m.head) for m in members.members} - {None}
        if kinds and kinds <= NO_SPACING_KINDS:
            shown = "/".join(sorted(k.upper() for k in kinds if k))
            raise UploadError(
                422,
                f"{relabel('upload', filename)} holds {shown} slices, which do not say how large a voxel is: send "
                '"spacing": [z, y, x] in millimetres in params (DICOM series and TIFF stacks with resolution '
                "tags carry it)",
            )
    return f"{summary.kind}, {summary.files} files, {summary.images} images, {summary.dicom} DICOM"


def _label_map(path: Path, filename: str | None, params: JobParams) -> str | None:
    """The summary of a label-map upload, None for another upload (a CT).

    Raises:
        UploadError: 422 for a float NIfTI, a zip of several label maps, ``"labels": true`` without a label map,
            or a label map sent with ``pieces`` or ``defect`` (which work on a CT).
    """
    from engine.errors import InputError
    from engine.io.archive import InputLimits, open_members
    from engine.labels.uploads import find_label_upload

    shown = relabel("upload", filename)
    try:
        if path.is_file() and zipfile.is_zipfile(path):  # names, counts and declared sizes first, as for any zip
            open_members(path, InputLimits(), heads_only=True).close()
        found = find_label_upload(path, shown, force=bool(params.labels))
    except InputError as exc:
        raise UploadError(422, relabel(str(exc), filename)) from None
    if found is None:
        return None
    if params.pieces is not None or params.defect is not None:
        raise UploadError(
            422, f"{shown} is a label map: pieces and defect work on a CT's model; send the CT, or leave them out"
        )
    return found.describe()
