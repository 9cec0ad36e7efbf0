"""glTF export: GLB layout, units (m), axis convention, winding, index types; Draco extension and round trip."""

from __future__ import annotations

import io
import json
import struct

import DracoPy
import numpy as np
import pytest
import trimesh
from pygltflib import GLTF2
from scipy.spatial import cKDTree

from engine.errors import InputError
from engine.export import EXPORTERS
from engine.export.draco import EXTENSION, to_draco_glb
from engine.export.glb import GLTF_FROM_XYZ, to_glb

CENTER_XYZ_MM = np.array([30.0, -20.0, 100.0])


def _sphere_zyx(radius_mm: float = 10.0, subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere (outward faces in x, y, z) at ``CENTER_XYZ_MM``, as an engine mesh (z, y, x)."""
    ico = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius_mm)
    xyz = ico.vertices + CENTER_XYZ_MM
    return xyz[:, ::-1].astype(np.float32), ico.faces.astype(np.int32)


def _torus_zyx(nu: int, nv: int, big: float = 40.0, small: float = 12.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed torus grid with 2 * nu * nv triangles, outward in (x, y, z), as an engine mesh."""
    u, v = np.meshgrid(np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / nv, indexing="ij")
    ring = big + small * np.cos(v)
    xyz = np.stack([ring * np.cos(u), ring * np.sin(u), small * np.sin(v)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, ((i + 1) % nu) * nv + j
    c, d = ((i + 1) % nu) * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    mesh = trimesh.Trimesh(xyz, faces, process=False)
    if mesh.volume < 0:
        faces = faces[:, ::-1]
    return xyz[:, ::-1].astype(np.float32), faces.astype(np.int32)


def _chunks(data: bytes) -> tuple[dict, bytes]:
    """Check the GLB header and chunk alignment; return the JSON document and the BIN chunk."""
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert magic == 0x46546C67 and version == 2 and length == len(data)
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0
    text = data[20 : 20 + json_len]
    assert text.rstrip(b" ").endswith(b"}") and len(text) - len(text.rstrip(b" ")) < 4  # padded with spaces
    doc = json.loads(text)
    bin_at = 20 + json_len
    bin_len, bin_type = struct.unpack_from("<II", data, bin_at)
    assert bin_type == 0x004E4942 and bin_len % 4 == 0 and bin_at + 8 + bin_len == len(data)
    assert doc["buffers"][0]["byteLength"] <= bin_len < doc["buffers"][0]["byteLength"] + 4
    return doc, data[bin_at + 8 : bin_at + 8 + bin_len]


def _accessor(doc: dict, binary: bytes, index: int) -> np.ndarray:
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    dtype = {5126: "<f4", 5123: "<u2", 5125: "<u4"}[acc["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3}[acc["type"]]
    start = view["byteOffset"] + acc.get("byteOffset", 0)
    assert start % np.dtype(dtype).itemsize == 0
    flat = np.frombuffer(binary, dtype, acc["count"] * width, start)
    return flat.reshape(-1, width) if width > 1 else flat


def test_rotation_is_proper() -> None:
    np.testing.assert_allclose(np.linalg.det(GLTF_FROM_XYZ), 1.0)
    np.testing.assert_allclose(GLTF_FROM_XYZ @ GLTF_FROM_XYZ.T, np.eye(3))


def test_glb_layout_parses_and_matches_document() -> None:
    verts, faces = _sphere_zyx()
    data = to_glb(verts, faces, name="femur")
    doc, binary = _chunks(data)
    assert doc["asset"] == {"version": "2.0", "generator": "bonemesh"}
    assert doc["nodes"][0]["name"] == "femur" and doc["meshes"][0]["name"] == "femur"
    prim = doc["meshes"][0]["primitives"][0]
    assert prim["mode"] == 4 and set(prim["attributes"]) == {"POSITION", "NORMAL"}
    assert [v["target"] for v in doc["bufferViews"]] == [34962, 34962, 34963]
    material = doc["materials"][prim["material"]]
    assert material["doubleSided"] is False and material["pbrMetallicRoughness"]["metallicFactor"] == 0.0
    pos_acc = doc["accessors"][prim["attributes"]["POSITION"]]
    pos = _accessor(doc, binary, prim["attributes"]["POSITION"])
    np.testing.assert_array_equal(pos_acc["min"], pos.min(axis=0))
    np.testing.assert_array_equal(pos_acc["max"], pos.max(axis=0))
    normals = _accessor(doc, binary, prim["attributes"]["NORMAL"])
    assert len(normals) == len(verts) and normals.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    indices = _accessor(doc, binary, prim["indices"])
    assert indices.dtype == np.uint16 and len(indices) == faces.size
    np.testing.assert_array_equal(indices.reshape(-1, 3), faces)

    gltf = GLTF2.load_from_bytes(data)
    assert gltf.asset.generator == "bonemesh" and len(gltf.meshes[0].primitives) == 1
    assert gltf.binary_blob()[: len(binary)] == binary[: len(gltf.binary_blob())]


def test_glb_units_axes_and_winding_with_trimesh() -> None:
    verts, faces = _sphere_zyx(radius_mm=10.0)
    scene = trimesh.load(io.BytesIO(to_glb(verts, faces)), file_type="glb", process=False)
    mesh = scene.to_geometry() if isinstance(scene, trimesh.Scene) else scene
    assert len(mesh.faces) == len(faces) and len(mesh.vertices) == len(verts)
    x, y, z = CENTER_XYZ_MM * 1e-3
    center = mesh.vertices.mean(axis=0)
    np.testing.assert_allclose(center, [x, z, -y], atol=1e-6)  # glTF (X, Y, Z) = (x, z, -y)
    np.testing.assert_allclose(np.linalg.norm(mesh.vertices - center, axis=1), 0.01, rtol=1e-5)
    assert mesh.is_watertight and mesh.volume > 0  # outward winding survives the rotation
    np.testing.assert_allclose(mesh.volume, 4 / 3 * np.pi * 0.01**3, rtol=0.03)
    # computed normals point outward
    doc, binary = _chunks(to_glb(verts, faces))
    normals = _accessor(doc, binary, 1)
    pos = _accessor(doc, binary, 0)
    radial = (pos - center) / np.linalg.norm(pos - center, axis=1, keepdims=True)
    assert (np.sum(normals * radial, axis=1) > 0.99).all()


def test_glb_axis_convention_single_triangle() -> None:
    # vertices in (z, y, x) mm; glTF positions must be (x, z, -y) m
    verts = np.array([[3.0, 2.0, 1.0], [0.0, 0.0, 5.0], [0.0, 7.0, 0.0]], np.float32)
    faces = np.array([[0, 1, 2]], np.int32)
    normals_zyx = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -3.0]], np.float32)  # +z, +y, -x
    doc, binary = _chunks(to_glb(verts, faces, normals_zyx))
    np.testing.assert_allclose(
        _accessor(doc, binary, 0), [[0.001, 0.003, -0.002], [0.005, 0.0, 0.0], [0.0, 0.0, -0.007]], atol=1e-9
    )
    # given normals are rotated like positions and normalised: z -> +Y, y -> -Z, x -> +X
    np.testing.assert_allclose(_accessor(doc, binary, 1), [[0, 1, 0], [0, 0, -1], [-1, 0, 0]], atol=1e-7)
    # computed normal of this triangle agrees with the rotated (x, y, z) face normal
    doc, binary = _chunks(to_glb(verts, faces))
    xyz = verts[:, ::-1].astype(np.float64)
    n = np.cross(xyz[1] - xyz[0], xyz[2] - xyz[0])
    expected = GLTF_FROM_XYZ @ (n / np.linalg.norm(n))
    np.testing.assert_allclose(_accessor(doc, binary, 1), np.tile(expected, (3, 1)), atol=1e-6)


@pytest.mark.parametrize(("n_verts", "ctype", "dtype"), [(65535, 5123, "<u2"), (65536, 5125, "<u4")])
def test_glb_index_type_threshold(n_verts: int, ctype: int, dtype: str) -> None:
    rng = np.random.default_rng(0)
    verts = rng.random((n_verts, 3), dtype=np.float32) * 100
    faces = np.array([[0, 1, n_verts - 1], [n_verts - 1, 1, 2]], np.int32)
    doc, binary = _chunks(to_glb(verts, faces))
    acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]
    assert acc["componentType"] == ctype and acc["count"] == 6
    np.testing.assert_array_equal(_accessor(doc, binary, 2), faces.ravel())
    assert doc["bufferViews"][2]["byteOffset"] % 4 == 0


def test_glb_rejects_bad_input() -> None:
    with pytest.raises(InputError):
        to_glb(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    with pytest.raises(InputError):
        to_glb(np.zeros((3, 3), np.float32), np.array([[0, 1, 3]], np.int32))
    with pytest.raises(InputError):
        to_glb(np.zeros((3, 3), np.float32), np.array([[0, 1, 2]], np.int32), np.zeros((2, 3), np.float32))


def test_registry() -> None:
    assert EXPORTERS["glb"] is to_glb and EXPORTERS["draco_glb"] is to_draco_glb and "stl" in EXPORTERS


def _draco_decode(data: bytes) -> tuple[dict, DracoPy.DracoMesh]:
    doc, binary = _chunks(data)
    assert doc["extensionsUsed"] == [EXTENSION] and doc["extensionsRequired"] == [EXTENSION]
    ext = doc["meshes"][0]["primitives"][0]["extensions"][EXTENSION]
    view = doc["bufferViews"][ext["bufferView"]]
    return doc, DracoPy.decode(binary[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])


def test_draco_glb_round_trip() -> None:
    verts, faces = _sphere_zyx(radius_mm=10.0, subdivisions=4)
    bits = 14
    data = to_draco_glb(verts, faces, quantization_bits=bits)
    doc, decoded = _draco_decode(data)
    prim = doc["meshes"][0]["primitives"][0]
    ext = prim["extensions"][EXTENSION]
    assert set(ext["attributes"]) == {"POSITION", "NORMAL"}
    by_id = {a["unique_id"]: a for a in decoded.attributes}
    assert by_id[ext["attributes"]["POSITION"]]["attribute_type"] == int(DracoPy.AttributeType.POSITION)
    assert by_id[ext["attributes"]["NORMAL"]]["attribute_type"] == int(DracoPy.AttributeType.NORMAL)
    for key in ("POSITION", "NORMAL"):
        acc = doc["accessors"][prim["attributes"][key]]
        assert "bufferView" not in acc and acc["count"] == len(decoded.points) and acc["type"] == "VEC3"
    idx = doc["accessors"][prim["indices"]]
    assert "bufferView" not in idx and idx["count"] == faces.size and idx["componentType"] == 5123
    assert len(decoded.faces) == len(faces) and len(decoded.points) == len(verts)

    # positions within the quantisation error, in metres, in the glTF frame
    pos = np.asarray(by_id[ext["attributes"]["POSITION"]]["data"], np.float64)
    expected = (verts[:, ::-1].astype(np.float64) @ GLTF_FROM_XYZ.T) * 1e-3
    step = np.ptp(expected, axis=0).max() / (2**bits - 1)
    dist, _ = cKDTree(expected).query(pos)  # Draco reorders vertices
    assert dist.max() <= step * np.sqrt(3) / 2 + 1e-7
    acc = doc["accessors"][prim["attributes"]["POSITION"]]
    np.testing.assert_allclose(acc["min"], pos.min(axis=0), atol=1e-7)
    np.testing.assert_allclose(acc["max"], pos.max(axis=0), atol=1e-7)
    center = pos.mean(axis=0)
    np.testing.assert_allclose(np.linalg.norm(pos - center, axis=1), 0.01, atol=2 * step)

    # normals: outward, unit to within the normal quantisation; faces still wound outward
    normals = np.asarray(by_id[ext["attributes"]["NORMAL"]]["data"], np.float64)
    radial = (pos - center) / np.linalg.norm(pos - center, axis=1, keepdims=True)
    assert (np.sum(normals * radial, axis=1) > 0.99).all()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=5e-3)
    mesh = trimesh.Trimesh(pos, decoded.faces, process=False)
    assert mesh.is_watertight and mesh.volume > 0

    gltf = GLTF2.load_from_bytes(data)
    assert gltf.extensionsRequired == [EXTENSION]


def test_draco_positions_only() -> None:
    verts, faces = _sphere_zyx()
    doc, decoded = _draco_decode(to_draco_glb(verts, faces, include_normals=False))
    prim = doc["meshes"][0]["primitives"][0]
    assert set(prim["attributes"]) == {"POSITION"} and set(prim["extensions"][EXTENSION]["attributes"]) == {"POSITION"}
    assert decoded.normals is None and len(decoded.faces) == len(faces)


def test_draco_much_smaller_than_glb() -> None:
    verts, faces = _torus_zyx(512, 130)  # 133k triangles, 66.5k vertices: uint32 indices
    assert len(faces) >= 100_000 and len(verts) >= 65536
    plain = to_glb(verts, faces)
    draco = to_draco_glb(verts, faces)
    assert len(draco) * 5 < len(plain), (len(draco), len(plain))
    doc, decoded = _draco_decode(draco)
    assert len(decoded.faces) == len(faces) and len(decoded.points) == len(verts)
    assert doc["accessors"][doc["meshes"][0]["primitives"][0]["indices"]]["componentType"] == 5125
