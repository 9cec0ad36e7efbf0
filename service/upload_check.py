"""What can be refused about an upload before it is queued: not an archive, unsafe names, too many members, a bomb
(by the declared sizes: member and whole-archive ratios, total expanded size), nothing to build from, or an image
stack that certainly needs a voxel size and was sent without one. Loading checks the rest (actual bytes, shapes).
"""

from __future__ import annotations

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
