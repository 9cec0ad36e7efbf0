"""Checks of what the service hands out: problem documents, job records, downloads (GLB, Draco GLB, STL, report)."""

from __future__ import annotations

import datetime as dt
import io
import json
import struct
import tempfile
from pathlib import Path
from typing import Any

import DracoPy
import httpx
import numpy as np
import trimesh

from tests.service.procs import OUTPUT_NAMES

PHONE_BUDGET = 100_000
AR_BUDGET = 50_000
DRACO = "KHR_draco_mesh_compression"


def assert_problem(resp: httpx.Response, status: int | tuple[int, ...]) -> dict[str, Any]:
    """An application/problem+json error with the expected status and a human-readable detail."""
    allowed = (status,) if isinstance(status, int) else status
    assert resp.status_code in allowed, f"expected {allowed}, got {resp.status_code}: {resp.text[:2000]}"
    ctype = resp.headers.get("content-type", "")
    assert ctype.startswith("application/problem+json"), f"content-type {ctype!r}: {resp.text[:500]}"
    body = resp.json()
    for key in ("type", "title", "status", "detail"):
        assert key in body, f"problem document lacks {key!r}: {body}"
    assert body["status"] == resp.status_code, body
    assert isinstance(body["detail"], str) and body["detail"].strip(), body
    assert body["type"] == f"urn:bonemesh:problem:{body.get('code')}", body  # one stable type per code, never blank
    return body


def parse_time(text: str | None) -> dt.datetime | None:
    """An ISO 8601 timestamp (aware), or None."""
    if text is None:
        return None
    value = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    return value if value.tzinfo else value.replace(tzinfo=dt.UTC)


def assert_succeeded(job: dict[str, Any], base_url: str) -> dict[str, dict[str, Any]]:
    """A succeeded job record: timestamps in order, no error, the five outputs with absolute signed links.

    Returns:
        The outputs by name.
    """
    assert job["state"] == "succeeded", json.dumps(job, indent=1)
    assert job["progress"] == 100, job
    assert job["error"] is None, job
    created, started, finished = (parse_time(job[k]) for k in ("created_at", "started_at", "finished_at"))
    assert created is not None and started is not None and finished is not None, job
    assert created <= started <= finished, job
    outputs = {o["name"]: o for o in job["outputs"]}
    assert sorted(outputs) == sorted(OUTPUT_NAMES), job["outputs"]
    for out in outputs.values():
        assert out["url"].startswith(f"{base_url}/v1/files/"), out
        assert out["bytes"] > 0 and out["media_type"] and out["kind"], out
    for name in ("model.stl", "model.glb", "phone.glb", "ar.glb"):
        assert isinstance(outputs[name]["triangles"], int) and outputs[name]["triangles"] > 0, outputs[name]
    assert outputs["phone.glb"]["triangles"] <= PHONE_BUDGET, outputs["phone.glb"]
    assert outputs["ar.glb"]["triangles"] <= AR_BUDGET, outputs["ar.glb"]
    return outputs


def download(client: httpx.Client, output: dict[str, Any]) -> bytes:
    """GET a signed link (the client must carry no API key) and check the headers of an attachment."""
    assert "x-api-key" not in client.headers
    resp = client.get(output["url"])
    assert resp.status_code == 200, f"{output['name']}: {resp.status_code} {resp.text[:500]}"
    disposition = resp.headers.get("content-disposition", "")
    assert disposition.startswith("attachment") and output["name"] in disposition, disposition
    assert resp.headers.get("content-type", "").startswith(output["media_type"]), resp.headers
    assert resp.headers.get("etag"), resp.headers
    assert len(resp.content) == output["bytes"], (len(resp.content), output)
    return resp.content


def glb_document(data: bytes) -> tuple[dict[str, Any], bytes]:
    """The JSON chunk and BIN chunk of a GLB (header checked)."""
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(data)), "not a glTF 2.0 binary"
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A
    doc = json.loads(data[20 : 20 + json_len])
    bin_at = 20 + json_len
    bin_len, bin_type = struct.unpack_from("<II", data, bin_at)
    assert bin_type == 0x004E4942
    return doc, data[bin_at + 8 : bin_at + 8 + bin_len]


def decode_draco_glb(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Positions (m, glTF axes) and faces of a Draco-compressed GLB with one primitive."""
    doc, binary = glb_document(data)
    assert DRACO in doc.get("extensionsRequired", []), doc.get("extensionsRequired")
    (mesh,) = doc["meshes"]
    (prim,) = mesh["primitives"]
    view = doc["bufferViews"][prim["extensions"][DRACO]["bufferView"]]
    start = view.get("byteOffset", 0)
    decoded = DracoPy.decode(binary[start : start + view["byteLength"]])
    points = np.asarray(decoded.points, dtype=np.float64).reshape(-1, 3)
    faces = np.asarray(decoded.faces, dtype=np.int64).reshape(-1, 3)
    assert len(faces) > 0 and np.isfinite(points).all()
    assert faces.min() >= 0 and faces.max() < len(points)
    return points, faces


def load_glb(data: bytes) -> trimesh.Trimesh:
    """A plain (uncompressed) GLB as one mesh, in metres."""
    scene = trimesh.load(io.BytesIO(data), file_type="glb", force="scene")
    meshes = [g for g in scene.dump() if isinstance(g, trimesh.Trimesh)]
    assert meshes, "the GLB holds no mesh"
    return trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]


def load_stl(data: bytes) -> trimesh.Trimesh:
    """A binary STL without merging or repair (so watertightness is the file's own)."""
    n = struct.unpack_from("<I", data, 80)[0]
    assert len(data) == 84 + 50 * n, "binary STL length does not match its triangle count"
    return trimesh.load(io.BytesIO(data), file_type="stl")


def grid_from_patient(points_xyz: np.ndarray, frame: dict[str, Any] | None) -> np.ndarray:
    """Patient (LPS mm) points back in the scan's grid (x, y, z) mm through report.json's ``frame`` (its
    ``patient_from_grid_xyz``, ``engine.orient``); no frame: the points are already in the grid."""
    xyz = np.asarray(points_xyz, dtype=np.float64)
    if frame is None:
        return xyz
    m = np.asarray(frame["patient_from_grid_xyz"], dtype=np.float64)
    assert m.shape == (4, 4) and np.allclose(m[3], [0, 0, 0, 1]), f"not an affine 4x4: {m.tolist()}"
    return np.linalg.solve(m[:3, :3], (xyz - m[:3, 3]).T).T


def assert_mesh_in_scan_mm(
    mesh: trimesh.Trimesh,
    shape_zyx: tuple[int, int, int],
    spacing_zyx_mm: tuple[float, float, float],
    frame: dict[str, Any] | None = None,
) -> None:
    """Bounds (x, y, z) in mm inside the scan's extent (one voxel of slack for the closed borders), and filling a
    good part of it (a model in metres or in voxels would not).

    The STL lies in the patient frame (a DICOM series at its ImagePositionPatient, far from the origin): with
    ``frame`` (report.json's) its vertices are mapped back to the grid first, so the grid box is compared where
    the model was placed, for any orientation.
    """
    extent_xyz = np.array([(n - 1) * s for n, s in zip(shape_zyx, spacing_zyx_mm, strict=True)])[::-1]
    voxel_xyz = np.array(spacing_zyx_mm)[::-1]
    grid = grid_from_patient(mesh.vertices, frame)
    lo, hi = grid.min(axis=0), grid.max(axis=0)
    where = f"(patient bounds {mesh.bounds.tolist()} mm, frame {frame})" if frame is not None else ""
    assert (lo >= -voxel_xyz - 1e-3).all() and (hi <= extent_xyz + voxel_xyz + 1e-3).all(), (
        f"grid bounds {[lo.tolist(), hi.tolist()]} mm outside the scan's extent {extent_xyz.tolist()} mm {where}"
    )
    assert ((hi - lo) >= 0.3 * extent_xyz).all(), (
        f"model size {(hi - lo).tolist()} mm is far smaller than the scan's {extent_xyz.tolist()} mm (not in mm?)"
    )


def check_outputs(
    anon: httpx.Client,
    outputs: dict[str, dict[str, Any]],
    shape_zyx: tuple[int, int, int],
    spacing_zyx_mm: tuple[float, float, float],
) -> dict[str, Any]:
    """Download every output through its signed link and check it; returns report.json."""
    files = {name: download(anon, out) for name, out in outputs.items()}
    report = json.loads(files["report.json"])
    frame = report["frame"]  # where model.stl lies: grid -> patient LPS mm

    stl = load_stl(files["model.stl"])
    assert len(stl.faces) == outputs["model.stl"]["triangles"]
    assert stl.is_watertight, "model.stl is not watertight"
    assert stl.is_winding_consistent and stl.volume > 0, "model.stl faces are not consistently outward"
    assert_mesh_in_scan_mm(stl, shape_zyx, spacing_zyx_mm, frame)
    # the glTF files are centred on the STL's box, and the report keeps the centre (a glTF point maps back)
    np.testing.assert_allclose(frame["gltf_centre_lps_mm"], stl.bounds.mean(axis=0), atol=1e-3)
    size_mm = np.sort(stl.extents)

    points_m, faces = decode_draco_glb(files["phone.glb"])
    assert len(faces) == outputs["phone.glb"]["triangles"] <= PHONE_BUDGET
    phone_size = np.sort(points_m.max(axis=0) - points_m.min(axis=0)) * 1000.0  # glTF is in metres
    np.testing.assert_allclose(phone_size, size_mm, rtol=0.05, err_msg="phone.glb is not the model in metres")

    for name, budget in (("model.glb", None), ("ar.glb", AR_BUDGET)):
        mesh = load_glb(files[name])
        assert len(mesh.faces) == outputs[name]["triangles"], name
        if budget is not None:
            assert len(mesh.faces) <= budget, name
        np.testing.assert_allclose(np.sort(mesh.extents) * 1000.0, size_mm, rtol=0.05, err_msg=name)

    check_viewer_files(files, outputs, size_mm)
    assert report["input"]["shape_zyx"] == list(shape_zyx), report["input"]
    np.testing.assert_allclose(report["input"]["spacing_zyx_mm"], spacing_zyx_mm, rtol=1e-4)
    assert {"gaussian", "isosurface", "decimate", "smooth"} <= set(report["stage_seconds"]), report["stage_seconds"]
    assert report["mesh"]["watertight"] is True
    assert report["mesh"]["n_faces"] == outputs["model.stl"]["triangles"]
    return report


def check_viewer_files(files: dict[str, bytes], outputs: dict[str, dict[str, Any]], size_mm: np.ndarray) -> None:
    """The meshopt GLB decodes to the phone model in metres, the USDZ holds the AR model (metres, +Y up), and the
    thumbnail is a PNG of a few hundred pixels that shows something."""
    import imageio.v3 as iio
    from pxr import Usd, UsdGeom

    from engine.export.meshopt import read_meshopt_glb

    points, _, faces = read_meshopt_glb(files["phone_meshopt.glb"])
    assert len(faces) == outputs["phone_meshopt.glb"]["triangles"] == outputs["phone.glb"]["triangles"]
    np.testing.assert_allclose(np.sort(np.ptp(points, axis=0)) * 1000.0, size_mm, rtol=0.05)
    path = Path(tempfile.mkdtemp()) / "model.usdz"
    path.write_bytes(files["model.usdz"])
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    (mesh,) = [UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert len(mesh.GetFaceVertexCountsAttr().Get()) == outputs["model.usdz"]["triangles"]
    pts = np.asarray(mesh.GetPointsAttr().Get())
    np.testing.assert_allclose(np.sort(np.ptp(pts, axis=0)) * 1000.0, size_mm, rtol=0.05)
    image = iio.imread(files["preview.png"])
    assert image.ndim == 3 and image.shape[2] == 4 and 128 <= image.shape[0] <= 1024, image.shape
    assert 0.05 < (image[..., 3] > 0).mean() < 0.95, "the thumbnail shows nothing, or nothing but the model"
