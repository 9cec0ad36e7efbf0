"""OME-Zarr images (OME-NGFF v0.4 on Zarr v2, v0.5 on Zarr v3) -> :class:`engine.types.Volume`, read slab by slab.

An OME-Zarr image is a Zarr group whose ``multiscales`` metadata (v0.4: the group's attributes; v0.5: under their
``ome`` key) lists its resolution levels, each an array with its own ``coordinateTransformations`` (a ``scale``
and optionally a ``translation`` per axis, in the axes' units, then those of the multiscale as a whole). The
reader is the maintained ``zarr`` package (zarr>=3 reads v2 and v3 stores): it opens a local folder (the image
itself, a folder holding one, a bioformats2raw layout's image ``0``, or one level's array folder,
``scan.ome.zarr/1``), a zip of such a folder, or ``s3://bucket/key`` (through ``obstore``; see :func:`s3_store`
for the settings it reads).

The full-resolution level (the first listed) is read by default; ``level`` picks another by index or by its
path. The (z, y, x) voxel size in mm and the origin come from the level's transformations and the space axes'
units (micrometer, nanometer, ... converted to mm); axes ``t`` and ``c`` of size 1 are dropped. The volume is one
array allocated once (``allocate``, as for slice stacks), filled one row of z-chunks (or shards) at a time: zarr
fetches and decodes that row's chunks (at most its ``async.concurrency`` at once, 10 by default) and copies each
into its place in the array (the slab is passed as zarr's ``out``), so the peak is the volume plus a few decoded
chunks, a constant whatever the volume's size (8 MiB chunks: +55-70 MiB on Zarr v3, +130 MiB on v2, about +200 MiB
with 128 MiB shards; ``benchmarks/big_formats.py``). Data of a type the engine does not mesh are converted: float64
slab by slab, int32 and wider after a whole read (narrowed like a .npy).
"""

from __future__ import annotations

import os
import posixpath
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from engine.errors import InputError, NoSpacingError
from engine.io.archive import ZARR_MARKERS, InputLimits, Members, is_zarr_folder
from engine.types import Volume

__all__ = [
    "ZarrLevel",
    "ZarrSource",
    "is_remote",
    "is_zarr_folder",
    "load_ome_zarr",
    "open_level",
    "read_planes",
    "s3_store",
    "z_step",
    "zarr_in",
]

# the space units of OME-NGFF (UDUNITS-2 names) and common abbreviations: mm per unit as (numerator, denominator),
# so that 120 micrometer is 120 / 1000 mm, the float nearest 0.12, as a caller's 0.12 is
_UNIT_MM: dict[str, tuple[int, int]] = {
    "angstrom": (1, 10**7), "attometer": (1, 10**15), "centimeter": (10, 1), "decimeter": (100, 1),
    "exameter": (10**21, 1), "femtometer": (1, 10**12), "foot": (3048, 10), "gigameter": (10**12, 1),
    "hectometer": (10**5, 1), "inch": (254, 10), "kilometer": (10**6, 1), "megameter": (10**9, 1),
    "meter": (1000, 1), "micrometer": (1, 1000), "mile": (1_609_344, 1), "millimeter": (1, 1),
    "nanometer": (1, 10**6), "parsec": (30_856_775_814_913_673 * 10**3, 1), "petameter": (10**18, 1),
    "picometer": (1, 10**9), "terameter": (10**15, 1), "yard": (9144, 10), "yoctometer": (1, 10**21),
    "yottameter": (10**27, 1), "zeptometer": (1, 10**18), "zettameter": (10**24, 1),
    "mm": (1, 1), "cm": (10, 1), "m": (1000, 1), "um": (1, 1000), "\u00b5m": (1, 1000), "\u03bcm": (1, 1000),
    "micron": (1, 1000), "nm": (1, 10**6),
}  # fmt: skip
_NATIVE = (np.uint8, np.uint16, np.int16, np.float32)
SPACING_HINT = (
    'give the voxel size in mm in z, y, x order (CLI --voxel-size z=..,y=..,x=..; job params "spacing": [z, y, x]; '
    "Python spacing_zyx_mm=(z, y, x))"
)


def is_remote(path: str | Path) -> bool:
    """Whether ``path`` names an object store (``s3://bucket/key``) rather than a local file."""
    return isinstance(path, str) and path.lower().startswith("s3://")


@dataclass(frozen=True)
class ZarrSource:
    """Where a Zarr hierarchy is: ``kind`` "folder" (``root`` a folder), "zip" (``root`` a zip file) or "s3"
    (``root`` the URL); ``inner``: the node's path under the root ("" for the root itself)."""

    kind: str
    root: str
    inner: str = ""

    @property
    def label(self) -> str:
        name = self.root.rstrip("/").rsplit("/", 1)[-1] if self.kind == "s3" else Path(self.root).name
        return posixpath.join(name, self.inner) if self.inner else name


def zarr_in(members: Members, path: Path) -> ZarrSource | None:
    """The Zarr hierarchy in an input listed by ``engine.io.archive.open_members``: a folder that is one (listed as
    kind "ome-zarr"), or the top-most Zarr metadata among a zip's or a folder's files; None when there is none.

    Raises:
        InputError: a tar holding a Zarr hierarchy (read from a folder, a zip or s3:// only).
    """
    if members.kind == "ome-zarr":
        return ZarrSource("folder", str(path))
    names = [m.name for m in members.members] + list(members.ignored)  # .zattrs & co. are hidden files: ignored
    tops = sorted(
        (posixpath.dirname(n) for n in names if posixpath.basename(n) in ZARR_MARKERS),
        key=lambda d: (d.count("/") + (d != ""), d),
    )
    if not tops:
        return None
    if members.kind not in ("zip", "folder"):
        raise InputError(
            f"{path.name} holds a Zarr hierarchy ({tops[0] or 'at its top'}) in a {members.kind}: bonemesh reads "
            "OME-Zarr from a folder, a zip of it or s3://; unpack it or zip it"
        )
    if members.kind == "folder":
        return ZarrSource("folder", str(path / tops[0]) if tops[0] else str(path))
    return ZarrSource("zip", str(path), tops[0])


def s3_store(url: str) -> Any:
    """A read-only ``zarr.storage.ObjectStore`` over ``s3://bucket/key`` with the project's S3 settings, read from
    the environment (the engine reads no settings object): ``BONEMESH_S3_ENDPOINT_URL`` (a store other than AWS:
    path-style requests, plain HTTP allowed), the keys ``AWS_ACCESS_KEY_ID`` / ``AWS_SECRET_ACCESS_KEY`` (and
    ``AWS_SESSION_TOKEN``), the region ``AWS_REGION`` or ``AWS_DEFAULT_REGION`` (default us-east-1); without keys
    obstore's own chain (web identity, the instance's role).

    Raises:
        InputError: not an ``s3://bucket/...`` URL, or obstore is not installed.
    """
    bucket, _, key = url[len("s3://") :].partition("/")
    if not bucket:
        raise InputError(f"{url}: expected s3://bucket/path/to/image.ome.zarr")
    try:
        from obstore.store import S3Store
        from zarr.storage import ObjectStore
    except ImportError:
        raise InputError(f"{url}: reading from s3:// needs obstore (pip install 'bonemesh[s3]')") from None
    import datetime as dt

    options: dict[str, Any] = {"connect_timeout": "5s", "timeout": "120s"}
    config: dict[str, Any] = {}
    endpoint = os.environ.get("BONEMESH_S3_ENDPOINT_URL") or None
    if endpoint:
        config["endpoint"] = endpoint
        config["virtual_hosted_style_request"] = False
        options["allow_http"] = endpoint.lower().startswith("http://")
    config["region"] = os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION") or "us-east-1"
    retry = {"max_retries": 3, "retry_timeout": dt.timedelta(seconds=30)}
    store = S3Store(
        bucket,
        prefix=key.strip("/") or None,
        client_options=options,  # type: ignore[arg-type]
        retry_config=retry,  # type: ignore[arg-type]
        **config,
    )
    return ObjectStore(store, read_only=True)


def _store(src: ZarrSource) -> Any:
    """The zarr store of ``src``'s root."""
    from zarr.storage import LocalStore, ZipStore

    if src.kind == "s3":
        return s3_store(src.root)
    if src.kind == "zip":
        return ZipStore(src.root, mode="r")
    return LocalStore(src.root, read_only=True)


def _where(src: ZarrSource) -> str:
    """``src`` for messages: the URL and the endpoint for S3, else its name."""
    if src.kind != "s3":
        return src.label
    endpoint = os.environ.get("BONEMESH_S3_ENDPOINT_URL") or "AWS S3"
    return f"{src.root.rstrip('/')}{'/' + src.inner if src.inner else ''} (S3 store at {endpoint})"


def _error_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0][:300]}" if text else type(exc).__name__


@dataclass(frozen=True)
class Axis:
    """One axis of a multiscale: its name (lower case), type ("space", "time", "channel" or other) and unit."""

    name: str
    type: str
    unit: str | None


@dataclass(frozen=True)
class Multiscale:
    """The first ``multiscales`` entry of an image: its version, axes, level paths and transformations."""

    version: str
    axes: tuple[Axis, ...]
    paths: tuple[str, ...]
    transforms: tuple[list[Any], ...]  # each level's coordinateTransformations
    outer: list[Any]  # the multiscale's own (applied after each level's)


def _ome(attrs: dict[str, Any]) -> dict[str, Any]:
    """A v0.5 group's ``ome`` attributes ({} before v0.5)."""
    ome = attrs.get("ome")
    return ome if isinstance(ome, dict) else {}


def _multiscale(attrs: dict[str, Any], where: str) -> Multiscale | None:
    """The first multiscale in a group's attributes (v0.5: under ``ome``; v0.4 and before: at the top); None when
    there is no ``multiscales`` key.

    Raises:
        InputError: ``multiscales`` is there but malformed (no datasets, axes that are not a list, ...).
    """
    ome = _ome(attrs)
    entries = ome.get("multiscales", attrs.get("multiscales"))
    if entries is None:
        return None
    if not isinstance(entries, list) or not entries or not isinstance(entries[0], dict):
        raise InputError(f"{where}: its multiscales metadata is not a list of images (OME-NGFF)")
    ms = entries[0]
    version = str(ome.get("version") or ms.get("version") or "unknown")
    datasets = ms.get("datasets")
    if not isinstance(datasets, list) or not datasets or not all(isinstance(d, dict) and "path" in d for d in datasets):
        raise InputError(f"{where}: its multiscales metadata lists no datasets (resolution levels) with a path")
    raw_axes = ms.get("axes")
    if raw_axes is None:  # v0.1/v0.2: always (t, c, z, y, x)
        raw_axes = [{"name": n, "type": "time" if n == "t" else "channel" if n == "c" else "space"} for n in "tczyx"]
    if not isinstance(raw_axes, list):
        raise InputError(f"{where}: its multiscales axes are not a list")
    axes = []
    for a in raw_axes:
        if isinstance(a, str):  # v0.3: names only
            a = {"name": a, "type": "space" if a in "zyx" else "time" if a == "t" else "channel" if a == "c" else ""}
        if not isinstance(a, dict) or "name" not in a:
            raise InputError(f"{where}: an axis of its multiscales metadata has no name: {a!r}")
        unit = a.get("unit")
        axes.append(Axis(str(a["name"]).lower(), str(a.get("type") or "").lower(), None if unit is None else str(unit)))
    return Multiscale(
        version=version,
        axes=tuple(axes),
        paths=tuple(str(d["path"]) for d in datasets),
        transforms=tuple(list(d.get("coordinateTransformations") or []) for d in datasets),
        outer=list(ms.get("coordinateTransformations") or []),
    )


def _probe(store: Any, where: str) -> None:
    """One request for the node's metadata before zarr asks for several at once (so that a store that cannot be
    reached, or refuses the keys, is reported once, in one line, and not also by zarr's unawaited requests).

    Raises:
        InputError: the store cannot be reached or refuses the request (named, with a hint where no keys are set),
            or holds no Zarr metadata at the key.
    """
    import obstore
    from obstore.exceptions import NotFoundError

    for name in ZARR_MARKERS:
        try:
            obstore.head(store.store, name)
            return
        except (NotFoundError, FileNotFoundError):  # obstore raises the latter for a 404
            continue
        except Exception as exc:
            keys = os.environ.get("AWS_ACCESS_KEY_ID") or os.environ.get("AWS_WEB_IDENTITY_TOKEN_FILE")
            hint = "" if keys else "; no S3 keys are set (AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY)"
            raise InputError(f"{where} cannot be reached or read: {_error_line(exc)}{hint}") from None
    raise InputError(f"{where} holds no Zarr image: no zarr.json (Zarr v3) or .zgroup/.zattrs (Zarr v2) there")


def _open_image(src: ZarrSource) -> tuple[Any, Multiscale, str | None, ZarrSource]:
    """The image group, its multiscale, the level the path named (when it names a level's array) and the source
    the group was opened at.

    Raises:
        InputError: the store cannot be opened (named), holds no Zarr node, or no OME-Zarr image.
    """
    import zarr

    where = _where(src)
    try:
        store = _store(src)
        if src.kind == "s3":
            _probe(store, where)
        node = zarr.open(store=store, path=src.inner, mode="r")
    except InputError:
        raise
    except Exception as exc:
        if "NotFound" in type(exc).__name__:  # zarr's GroupNotFoundError & co.: reached, but nothing there
            raise InputError(
                f"{where} holds no Zarr image: no zarr.json (Zarr v3) or .zgroup/.zattrs (Zarr v2) there"
            ) from None
        what = "cannot be read as a Zarr hierarchy" if src.kind != "s3" else "cannot be reached or read"
        raise InputError(f"{where} {what}: {_error_line(exc)}") from None
    if isinstance(node, zarr.Array):  # one level's array: its parent is the image
        return _parent_image(src, where)
    return (*_image_group(node, src), None, src)


def _parent_image(src: ZarrSource, where: str) -> tuple[Any, Multiscale, str | None, ZarrSource]:
    """The image whose level ``src`` (an array) is, and that level's path.

    Raises:
        InputError: the array's parent is no OME-Zarr image (a bare array: no voxel size, no axes).
    """
    import zarr

    bare = InputError(f"{where} is a bare Zarr array, not an OME-Zarr image (no multiscales metadata above it)")
    if src.inner:
        named = posixpath.basename(src.inner.rstrip("/"))
        parent = ZarrSource(src.kind, src.root, posixpath.dirname(src.inner.rstrip("/")))
    elif src.kind == "s3" and "/" in src.root[5:].strip("/"):
        root, named = src.root.rstrip("/").rsplit("/", 1)
        parent = ZarrSource("s3", root)
    elif src.kind == "folder":
        named, parent = Path(src.root).name, ZarrSource("folder", str(Path(src.root).parent))
    else:
        raise bare
    try:
        group = zarr.open_group(store=_store(parent), path=parent.inner, mode="r")
        ms = _multiscale(dict(group.attrs), _where(parent))
    except InputError:
        raise
    except Exception:
        raise bare from None
    if ms is None:
        raise bare
    return group, ms, named, parent


def _image_group(group: Any, src: ZarrSource) -> tuple[Any, Multiscale]:
    """The group's multiscale image: the group itself, or a bioformats2raw layout's first image (``0``)."""
    attrs = dict(group.attrs)
    ms = _multiscale(attrs, _where(src))
    ome = _ome(attrs)
    if ms is None and ("bioformats2raw.layout" in attrs or "bioformats2raw.layout" in ome) and "0" in group:
        group = group["0"]
        ms = _multiscale(dict(group.attrs), _where(src) + "/0")
    if ms is None:
        kind = next((k for k in ("plate", "well", "labels") if k in attrs or k in ome), None)
        found = f"a {kind} collection, not an image; give one image's group" if kind else "no multiscales metadata"
        raise InputError(
            f"{_where(src)} is a Zarr group but not an OME-Zarr image: {found} (OME-NGFF v0.4 or v0.5 expected)"
        )
    return group, ms


def _pick_level(ms: Multiscale, level: int | str | None, where: str, shapes: Callable[[str], str]) -> int:
    """The index of the level asked for: an index (int, or digits that are no level's path) or a level's path.

    Raises:
        InputError: no such level (the message lists the levels and their shapes).
    """
    if level is None:
        return 0
    if isinstance(level, str) and level in ms.paths:
        return ms.paths.index(level)
    index = level if isinstance(level, int) else int(level) if str(level).isdigit() else None
    if index is not None and not isinstance(index, bool) and 0 <= index < len(ms.paths):
        return index
    listed = ", ".join(f"{i}: {p!r} ({shapes(p)})" for i, p in enumerate(ms.paths))
    raise InputError(f"{where} has no level {level!r}; its levels are {listed}")


def _affine(transforms: Sequence[Any], n: int, where: str) -> tuple[list[float], list[float]]:
    """The per-axis scale and translation that a list of coordinateTransformations composes to.

    Raises:
        InputError: a transformation given by path (a binary array), of an unknown type, or of the wrong length.
    """
    scale, shift = [1.0] * n, [0.0] * n
    for t in transforms:
        kind = t.get("type") if isinstance(t, dict) else None
        if kind == "identity":
            continue
        if kind not in ("scale", "translation"):
            raise InputError(f"{where}: coordinate transformation {t!r} is not a scale or a translation")
        values = t.get(kind)
        if values is None and "path" in t:
            raise InputError(f"{where}: its {kind} is stored in an array ({t['path']!r}); give it in the metadata")
        if not isinstance(values, list) or len(values) != n or not all(isinstance(v, int | float) for v in values):
            raise InputError(f"{where}: its {kind} {values!r} is not {n} numbers, one per axis")
        if kind == "scale":
            scale = [s * float(v) for s, v in zip(scale, values, strict=True)]
            shift = [s * float(v) for s, v in zip(shift, values, strict=True)]
        else:
            shift = [s + float(v) for s, v in zip(shift, values, strict=True)]
    return scale, shift


def _space_axes(ms: Multiscale, shape: tuple[int, ...], where: str) -> tuple[int, int, int]:
    """The array axes of z, y and x; every other axis must be of size 1.

    Raises:
        InputError: not three space axes named z, y, x, or another axis (channels, time points) larger than 1.
    """
    names = [a.name for a in ms.axes]
    if len(names) != len(shape):
        raise InputError(
            f"{where}: its metadata names {len(names)} axes ({', '.join(names)}), its array has {len(shape)}"
        )
    space = [a.name for a in ms.axes if a.type == "space" or (not a.type and a.name in "zyx")]
    if sorted(space) != ["x", "y", "z"]:
        raise InputError(
            f"{where}: expected three space axes named z, y, x, got {', '.join(space) or 'none'} "
            f"(axes {', '.join(names)}): bonemesh meshes 3-D volumes"
        )
    for a, n in zip(ms.axes, shape, strict=True):
        if a.name not in "zyx" and n != 1:
            what = {"channel": "channels", "time": "time points"}.get(a.type, f"entries along {a.name}")
            raise InputError(f"{where}: it holds {n} {what} (axis {a.name!r}); bonemesh meshes one 3-D volume")
    return names.index("z"), names.index("y"), names.index("x")


def _geometry(
    ms: Multiscale, index: int, zyx: tuple[int, int, int], where: str
) -> tuple[tuple[float, float, float] | None, tuple[float, float, float], str]:
    """The level's voxel size (z, y, x) and origin (x, y, z) in mm (None and 0 where the units are missing), and
    what was found, for messages.

    Raises:
        InputError: an unknown or non-length unit on a space axis.
    """
    n = len(ms.axes)
    scale, shift = _affine(ms.transforms[index], n, f"{where} (level {ms.paths[index]!r})")
    outer_scale, outer_shift = _affine(ms.outer, n, where)
    scale = [s * o for s, o in zip(scale, outer_scale, strict=True)]
    shift = [s * o + t for s, o, t in zip(shift, outer_scale, outer_shift, strict=True)]
    units: list[tuple[int, int] | None] = []
    for i in zyx:
        unit = ms.axes[i].unit
        if unit is not None and unit.strip().lower() not in _UNIT_MM:
            raise InputError(
                f"{where}: axis {ms.axes[i].name!r} has unit {unit!r}, not a length bonemesh knows (OME-NGFF space "
                "units: micrometer, nanometer, millimeter, ...)"
            )
        units.append(None if unit is None else _UNIT_MM[unit.strip().lower()])
    found = ", ".join(f"{ms.axes[i].name} {scale[i]:g} {ms.axes[i].unit or '(no unit)'}" for i in zyx)
    scaled = any(isinstance(t, dict) and t.get("type") == "scale" for t in [*ms.transforms[index], *ms.outer])
    if not scaled:  # v0.3 and before: no scale at all, not a voxel size of 1 unit
        return None, (0.0, 0.0, 0.0), "no scale"
    if any(u is None for u in units):
        return None, (0.0, 0.0, 0.0), found
    size = tuple(scale[i] * u[0] / u[1] for i, u in zip(zyx, units, strict=True) if u is not None)
    origin = tuple(shift[i] * u[0] / u[1] for i, u in zip(zyx, units, strict=True) if u is not None)
    return (size[0], size[1], size[2]), (origin[2], origin[1], origin[0]), found


def _spacing(
    call: tuple[float, float, float] | None, found: tuple[float, float, float] | None, text: str, where: str
) -> tuple[tuple[float, float, float], str]:
    """The voxel size used and where it came from: the caller's, else the metadata's (checked).

    Raises:
        NoSpacingError: neither; InputError: the metadata's is implausible.
    """
    from engine.params import check_spacing_zyx_mm

    if call is not None:
        return call, "call"
    if found is None and text == "no scale":
        raise NoSpacingError(f"{where}: its metadata give no scale (coordinateTransformations); {SPACING_HINT}")
    if found is None:
        raise NoSpacingError(f"{where}: its metadata give the scale ({text}) without a length unit; {SPACING_HINT}")
    try:
        return check_spacing_zyx_mm(found), "ome-zarr"
    except ValueError as exc:
        raise InputError(
            f"{where}: its metadata gives an implausible voxel size ({text}): {exc}; {SPACING_HINT}"
        ) from None


def _target_dtype(dtype: np.dtype[Any]) -> np.dtype[Any] | None:
    """The dtype the volume is read into slab by slab, in this machine's byte order (None: read whole, then narrowed
    like a .npy)."""
    if dtype.type in _NATIVE:
        return np.dtype(dtype.type)  # a big-endian Zarr v2 array is swapped slab by slab
    if dtype == np.bool_:
        return np.dtype(np.uint8)
    if dtype == np.int8:
        return np.dtype(np.int16)
    if dtype.kind == "f":
        return np.dtype(np.float32)
    return None


def _read_slabs(lv: ZarrLevel, out: np.ndarray, on_progress: Callable[[float], None] | None) -> None:
    """Fill ``out`` (z, y, x) from the level, a slab of whole z-chunks (shards) at a time, each chunk decoded by zarr
    into its place in ``out`` (a slab of another dtype goes through one slab-sized temporary)."""
    step = z_step(lv)
    nz = out.shape[0]
    for z0 in range(0, nz, step):
        z1 = min(nz, z0 + step)
        read_planes(lv, z0, z1, out[z0:z1])
        if on_progress is not None:
            on_progress(z1 / nz)


@dataclass(frozen=True)
class ZarrLevel:
    """One level of an OME-Zarr image, opened but not read (``open_level``): the zarr array, its z, y, x axes, the
    (z, y, x) shape, the dtype it is read into (None: read whole, then narrowed), the voxel size and origin (x, y, z)
    in mm, where they came from, and the volume's ``source`` entry."""

    arr: Any
    zyx: tuple[int, int, int]
    shape: tuple[int, int, int]
    target: np.dtype[Any] | None
    spacing: tuple[float, float, float]
    origin: tuple[float, float, float]
    where: str
    source: dict[str, Any]


def open_level(
    src: ZarrSource,
    *,
    level: int | str | None = None,
    spacing_zyx_mm: tuple[float, float, float] | None = None,
    limits: InputLimits | None = None,
) -> ZarrLevel:
    """Open one level of an OME-Zarr image and read its metadata (``load_ome_zarr`` reads it; ``engine.io.slabs``
    reads it slab by slab); the arguments and errors are ``load_ome_zarr``'s."""
    limits = limits or InputLimits()
    group, ms, named, src = _open_image(src)
    where = _where(src)

    def shape_of(p: str) -> str:
        try:
            return "x".join(str(n) for n in group[p].shape)
        except Exception:
            return "missing"

    index = _pick_level(ms, named if level is None else level, where, shape_of)
    try:
        arr = group[ms.paths[index]]
    except Exception as exc:
        raise InputError(f"{where}: level {ms.paths[index]!r} cannot be opened: {_error_line(exc)}") from None
    zyx = _space_axes(ms, tuple(arr.shape), where)
    found, origin, text = _geometry(ms, index, zyx, where)
    spacing, how = _spacing(spacing_zyx_mm, found, text, where)
    shape = (int(arr.shape[zyx[0]]), int(arr.shape[zyx[1]]), int(arr.shape[zyx[2]]))
    limits.check_voxels(shape, where)
    source = {
        "format": "ome-zarr",
        "container": src.kind,
        "ome_version": ms.version,
        "zarr_format": int(arr.metadata.zarr_format),
        "level": ms.paths[index],
        "levels": len(ms.paths),
        "dtype": str(arr.dtype),
        "spacing_from": how,
    }
    target = _target_dtype(np.dtype(arr.dtype))
    return ZarrLevel(arr, zyx, shape, target, spacing, origin, where, source)


def read_planes(
    lv: ZarrLevel,
    z0: int,
    z1: int,
    out: np.ndarray,
    ys: tuple[int, int] | None = None,
    xs: tuple[int, int] | None = None,
) -> None:
    """Planes ``z0:z1`` of the level into ``out`` ((z1 - z0, y, x), of ``lv.target``), decoded by zarr in place
    where the types agree; with ``ys`` and ``xs`` only rows ``ys[0]:ys[1]`` and columns ``xs[0]:xs[1]`` of them
    (zarr decodes only the chunks that hold them).

    Raises:
        InputError: the planes cannot be read (named).
    """
    from zarr.core.buffer import default_buffer_prototype

    arr, zyx = lv.arr, lv.zyx
    ys, xs = ys or (0, lv.shape[1]), xs or (0, lv.shape[2])
    cut = {zyx[0]: slice(z0, z1), zyx[1]: slice(*ys), zyx[2]: slice(*xs)}
    selection = tuple(cut.get(i, 0) for i in range(len(arr.shape)))
    view = out.transpose(sorted(range(3), key=lambda k: zyx[k]))  # out's axes in the array's order
    try:
        if arr.dtype == out.dtype:
            arr.get_basic_selection(selection, out=default_buffer_prototype().nd_buffer.from_numpy_array(view))
        else:
            view[...] = arr.get_basic_selection(selection)
    except Exception as exc:
        raise InputError(f"{lv.where}: slices {z0}-{z1 - 1} cannot be read: {_error_line(exc)}") from None


def z_step(lv: ZarrLevel) -> int:
    """Planes in one row of z-chunks (or shards): what one read decodes at least."""
    arr = lv.arr
    return int((getattr(arr, "shards", None) or arr.chunks)[lv.zyx[0]])


def load_ome_zarr(
    src: ZarrSource,
    *,
    level: int | str | None = None,
    spacing_zyx_mm: tuple[float, float, float] | None = None,
    limits: InputLimits | None = None,
    on_progress: Callable[[float], None] | None = None,
    allocate: Callable[[tuple[int, ...], np.dtype[Any]], np.ndarray] | None = None,
) -> Volume:
    """Load one level of an OME-Zarr image as a (z, y, x) :class:`Volume` (see the module docstring).

    Args:
        src: where the image is (``zarr_in``, or ``ZarrSource("s3", url)``).
        level: the level's index (0: full resolution, the default) or path; a path that names a level's array
            (``scan.ome.zarr/2``) picks that level unless ``level`` is given.
        spacing_zyx_mm: the voxel size of the level read, when the metadata lack units (it wins over them).
        limits: ``max_voxels`` is checked before anything is allocated.
        on_progress: called with the fraction of slices read.
        allocate: makes the (z, y, x) array (default ``np.empty``; see ``engine.io.load_volume``).

    Raises:
        InputError: unreadable store (named), no OME-Zarr image, a missing level, unknown units, several channels
            or time points, too many voxels; NoSpacingError: no length unit and no ``spacing_zyx_mm``.
    """
    from engine.io.stack import _allocated, _narrow

    lv = open_level(src, level=level, spacing_zyx_mm=spacing_zyx_mm, limits=limits)
    if lv.target is None:  # int32 & co.: read whole, then narrowed to what the engine meshes
        data = np.empty(lv.shape, np.dtype(lv.arr.dtype).newbyteorder("="))
        _read_slabs(lv, data, on_progress)
        data = _narrow(data)
    else:
        data = _allocated(allocate, lv.shape, lv.target)
        _read_slabs(lv, data, on_progress)
    return Volume(data=data, spacing_zyx_mm=lv.spacing, origin_mm=lv.origin, units="raw", source=lv.source)
