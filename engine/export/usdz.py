"""USDZ for iOS AR Quick Look (which reads USDZ, not glTF), written with Pixar's ``usd-core``.

The scene is the glTF files' (:mod:`engine.export.glb`): metres (``metersPerUnit = 1``), +Y up, the model centred
as ``write_outputs`` centres it, counter-clockwise outward triangles (USD's default orientation), vertex normals,
and one ``UsdPreviewSurface`` material in the bone colour. The stage is a binary ``.usdc`` layer packed with
``UsdUtils.CreateNewARKitUsdzPackage`` (uncompressed, 64-byte aligned, as ARKit requires).
"""

from __future__ import annotations

import struct
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.export.glb import BONE_MATERIAL, gltf_mesh


def _pxr() -> Any:
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdUtils, Vt
    except ImportError as exc:  # pragma: no cover - a dependency of the project
        raise ImportError("the USDZ export needs Pixar's USD: pip install usd-core") from exc
    return Gf, Sdf, Usd, UsdGeom, UsdShade, UsdUtils, Vt


def load_native() -> None:
    """Import USD's native library now: ``engine.export.files`` calls it when the exporter is looked up, on
    the thread that then starts the threads that encode (a first load from two threads at once can deadlock)."""
    _pxr()


def to_usdz(
    vertices_zyx_mm: npt.ArrayLike,
    faces: npt.ArrayLike,
    normals_zyx: npt.ArrayLike | None = None,
    *,
    name: str = "bone",
) -> bytes:
    """Encode a mesh as a USDZ package (metres, +Y up; the glTF files' frame).

    Args:
        vertices_zyx_mm: (V, 3) vertices in (z, y, x) order, mm.
        faces: (F, 3) vertex indices (outward with vertices in (x, y, z) order).
        normals_zyx: optional (V, 3) normals in (z, y, x) order; area-weighted vertex normals when None.
        name: the root prim's name.

    Returns:
        The .usdz file's bytes.

    Raises:
        InputError: an empty or malformed mesh.
    """
    Gf, Sdf, Usd, UsdGeom, UsdShade, UsdUtils, Vt = _pxr()
    positions, normals, tris = gltf_mesh(vertices_zyx_mm, faces, normals_zyx)
    positions = positions.astype(np.float32)
    with tempfile.TemporaryDirectory(prefix="bonemesh-usdz-") as folder:
        layer = str(Path(folder) / f"{name}.usdc")
        stage = Usd.Stage.CreateNew(layer)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        root = UsdGeom.Xform.Define(stage, f"/{name}")
        stage.SetDefaultPrim(root.GetPrim())
        mesh = UsdGeom.Mesh.Define(stage, f"/{name}/mesh")
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(positions))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tris), 3, dtype=np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tris.astype(np.int32).ravel()))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(normals))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # a polygon mesh, not a subdivision cage
        mesh.CreateDoubleSidedAttr(False)
        lo, hi = positions.min(axis=0), positions.max(axis=0)
        mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
        material = UsdShade.Material.Define(stage, f"/{name}/bone")
        shader = UsdShade.Shader.Define(stage, f"/{name}/bone/surface")
        shader.CreateIdAttr("UsdPreviewSurface")
        pbr = BONE_MATERIAL["pbrMetallicRoughness"]
        shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*pbr["baseColorFactor"][:3]))
        shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(float(pbr["roughnessFactor"]))
        shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(float(pbr["metallicFactor"]))
        material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
        stage.GetRootLayer().Save()
        package = str(Path(folder) / f"{name}.usdz")
        if not UsdUtils.CreateNewARKitUsdzPackage(Sdf.AssetPath(layer), package):
            raise RuntimeError("usd-core could not write the USDZ package")
        return fixed_zip_times(Path(package).read_bytes())


DOS_EPOCH = (0, 0x21)  # the zip format's time and date fields for 1980-01-01 00:00


def fixed_zip_times(data: bytes) -> bytes:
    """The package with every member's modification time set to ``DOS_EPOCH``, in place (same lengths, so the
    64-byte alignment of USDZ members stays): the same mesh gives the same bytes whenever it is written (the clock
    changed them at 2 s resolution)."""
    out = bytearray(data)
    end = out.rfind(b"PK\x05\x06")
    if end < 0:
        return data
    count, _size, cd = struct.unpack_from("<HII", out, end + 10)
    at = cd
    for _ in range(count):
        if out[at : at + 4] != b"PK\x01\x02":
            return data
        struct.pack_into("<HH", out, at + 12, *DOS_EPOCH)
        name_len, extra_len, comment_len = struct.unpack_from("<HHH", out, at + 28)
        (local,) = struct.unpack_from("<I", out, at + 42)
        if out[local : local + 4] == b"PK\x03\x04":
            struct.pack_into("<HH", out, local + 10, *DOS_EPOCH)
        at += 46 + name_len + extra_len + comment_len
    return bytes(out)
