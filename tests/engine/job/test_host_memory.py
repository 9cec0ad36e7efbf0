"""A host memory bound per job (issue 46): a scan over the bound's share for a whole scan is read slab by slab from
disk (``engine.io.slabs``) through the streamed plan, and its model is byte for byte the model of the same scan
loaded whole under the same device budget, from each kind of source; the level comes from the same samples; the
steps that need the whole scan are refused in one line naming the way out; on the CPU the device budget comes out
of the bound, and a bound too small says the smallest that works."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from engine.budget import Budget
from engine.errors import BudgetError, InputError
from engine.job import JobSpec, resolve_runtime, run_job
from engine.params import PreprocessParams, RoiParams
from tests.engine.cli.test_cli import run_cli

SHAPE = (40, 64, 64)
SPACING = (0.5, 0.5, 0.5)
DEVICE = 16 << 20  # the device budget both runs keep to (the same slabs: the same model)
# a bound whose share for a whole scan (0.1 %) is under the phantom's 320 KiB, with the device budget within it
BOUNDED = Budget(bytes=DEVICE, host_bytes=64 << 20, host_volume_share=0.001)
FORMATS = ("npy", "tiff-folder", "bigtiff", "ome-zarr")


@pytest.fixture(scope="module")
def scans(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The bone phantom (uint16, HU + 1024) in each format read slab by slab."""
    import tifffile

    from engine.data.phantom import bone_phantom
    from tests.engine.omezarr_factory import write_ome_zarr

    work = tmp_path_factory.mktemp("host_memory")
    vol = bone_phantom(SHAPE, workers=1)
    np.save(work / "scan.npy", vol)
    (work / "slices").mkdir()
    for k, plane in enumerate(vol):
        tifffile.imwrite(work / "slices" / f"slice_{k:03d}.tif", plane)
    tifffile.imwrite(work / "scan.tif", vol, bigtiff=True)
    write_ome_zarr(work / "scan.ome.zarr", vol, scale=[s * 1000 for s in SPACING], chunks=(8, 32, 32))
    return {
        "npy": work / "scan.npy",
        "tiff-folder": work / "slices",
        "bigtiff": work / "scan.tif",
        "ome-zarr": work / "scan.ome.zarr",
    }


def _spec(**recon: Any) -> JobSpec:
    spec = JobSpec()
    recon.setdefault("body", None)  # the phantom reads as HU + 1024: its body outline needs the whole scan
    return dataclasses.replace(
        spec,
        input=dataclasses.replace(spec.input, spacing_zyx_mm=SPACING),
        recon=dataclasses.replace(spec.recon, **recon),
    )


@pytest.fixture(scope="module")
def whole(scans: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, dict[str, Any]]:
    """The model of the scan loaded whole, under the same device budget."""
    out = tmp_path_factory.mktemp("whole")
    result = run_job(scans["npy"], out, _spec(), resolve_runtime("cpu", Budget(bytes=DEVICE)))
    assert result.report["memory"].get("out_of_core") is None
    return (out / "model.stl").read_bytes(), result.report


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_scan_read_slab_by_slab_gives_the_model_of_the_whole(
    scans: dict[str, Path], whole: tuple[bytes, dict[str, Any]], fmt: str, tmp_path: Path
) -> None:
    result = run_job(scans[fmt], tmp_path, _spec(), resolve_runtime("cpu", BOUNDED))
    report = result.report
    assert report["memory"]["out_of_core"] is True and report["memory"]["host_bound_bytes"] == 64 << 20
    assert report["input"]["source"]["read"] == "slab by slab (host memory bound)"
    stl, ref = whole
    assert (tmp_path / "model.stl").read_bytes() == stl  # the mesh's arrays, exactly
    assert report["iso_level"] == ref["iso_level"]
    for key in ("n_faces", "components", "euler", "watertight"):
        assert report["mesh"][key] == ref["mesh"][key], key
    assert report["warnings"] == ref["warnings"]


def test_through_the_plane_feeds_ring(
    scans: dict[str, Path], whole: tuple[bytes, dict[str, Any]], tmp_path: Path
) -> None:
    """The ring of planes a GPU's uploads go through (forced here on the CPU): planes decoded straight into it from
    the files, a slab longer than the ring read behind it; the same model."""
    ring = 5 * SHAPE[1] * SHAPE[2] * 2
    budget = dataclasses.replace(BOUNDED, feed_ring_bytes=ring)
    result = run_job(scans["tiff-folder"], tmp_path, _spec(), resolve_runtime("cpu", budget))
    assert result.report["memory"]["stream"]["feed"]["requests"] > 0
    assert (tmp_path / "model.stl").read_bytes() == whole[0]


def test_the_level_and_warnings_from_strided_samples_read_plane_by_plane(tmp_path: Path) -> None:
    """Large enough that the level's sample takes every 2nd voxel and the skin check's every 3rd: the samples read
    plane by plane are the whole scan's, and so are the detected HU offset, the level and the warnings."""
    from engine.io.slabs import open_slabs
    from engine.level import model_warnings, resolve_level
    from engine.params import IsoParams, ReconParams
    from engine.types import Volume

    rng = np.random.default_rng(3)
    shape = (230, 240, 250)  # 13.8 M voxels
    y, x = np.ogrid[: shape[1], : shape[2]]
    r = np.broadcast_to(np.hypot(y - 120, x - 125), shape)
    data = np.where(r < 100, 1024 + 40, 24).astype(np.uint16)  # air and soft tissue, HU + 1024
    data[(r > 60) & (r < 75)] = 1024 + 900  # a bone ring
    data += rng.integers(0, 30, size=shape, dtype=np.uint16)
    np.save(tmp_path / "ct.npy", data)
    sliced = open_slabs(tmp_path / "ct.npy", 0, spacing_zyx_mm=(1.0, 0.5, 0.5))
    assert sliced is not None
    loaded = Volume(data, (1.0, 0.5, 0.5), source=dict(sliced.source))
    for params in (ReconParams(), ReconParams(iso=IsoParams(preset="compact-bone", hu_offset=1024))):
        a, b = resolve_level(loaded, params), resolve_level(sliced, params)
        assert a == b and a.how.startswith(("bone preset", "preset"))
        assert model_warnings(loaded, a) == model_warnings(sliced, b)
    otsu = (data > 1024 + 400).astype(np.uint8) * 200 + (data % 7).astype(np.uint8)  # no offset: Otsu's level
    np.save(tmp_path / "otsu.npy", otsu)
    sliced = open_slabs(tmp_path / "otsu.npy", 0, spacing_zyx_mm=(1.0, 0.5, 0.5))
    assert sliced is not None
    a = resolve_level(Volume(otsu, (1.0, 0.5, 0.5)), ReconParams())
    assert a.how.startswith("Otsu") and a == resolve_level(sliced, ReconParams())
    sliced.data.close()


@pytest.mark.parametrize(
    ("change", "option"),
    [
        ({"body": "default"}, "--keep-outside-body"),
        ({"preprocess": PreprocessParams(threshold=100.0)}, "the slice preprocessing"),
    ],
)
def test_steps_that_need_the_whole_scan_are_refused_in_one_line(
    scans: dict[str, Path], tmp_path: Path, change: dict[str, Any], option: str
) -> None:
    from engine.params import BodyMaskParams

    spec = _spec()
    if "body" in change:
        spec = _spec(body=BodyMaskParams())
    else:
        spec = _spec(**change)
    with pytest.raises(InputError) as err:
        run_job(scans["npy"], tmp_path / "out", spec, resolve_runtime("cpu", BOUNDED))
    message = str(err.value)
    assert option in message and "needs the whole scan in memory" in message and "--max-host-bytes" in message
    assert "\n" not in message and not (tmp_path / "out" / "model.stl").exists()


@pytest.mark.parametrize(
    ("box", "share", "read_whole"),
    [(((4, 36), (8, 60), (0, 50)), 0.001, False), (((4, 36), (8, 60), (0, 50)), 0.004, True)],
)
def test_a_region_of_interest_of_a_scan_read_slab_by_slab(
    scans: dict[str, Path], tmp_path: Path, box: Any, share: float, read_whole: bool
) -> None:
    """A box of a scan over the bound is cut from the slabs as they are read (only the box's planes, cut to it), and
    read whole where the box fits the bound's share for a whole scan: the model of the same box of the scan loaded
    whole, byte for byte, either way."""
    spec = _spec()
    spec = dataclasses.replace(spec, input=dataclasses.replace(spec.input, roi=RoiParams(box)))
    ref = run_job(scans["npy"], tmp_path / "whole", spec, resolve_runtime("cpu", Budget(bytes=DEVICE)))
    bounded = dataclasses.replace(BOUNDED, host_volume_share=share)  # box 162 KiB, scan 320; share 64 or 262 KiB
    for fmt in ("npy", "ome-zarr"):
        result = run_job(scans[fmt], tmp_path / fmt, spec, resolve_runtime("cpu", bounded))
        assert bool(result.report["memory"].get("out_of_core")) is not read_whole, fmt
        assert result.report["input"]["shape_zyx"] == [32, 52, 50]
        assert (tmp_path / fmt / "model.stl").read_bytes() == (tmp_path / "whole" / "model.stl").read_bytes(), fmt
    assert ref.report["frame"] == result.report["frame"]  # the box's origin moved the same way


def test_on_the_cpu_the_device_budget_comes_out_of_the_bound() -> None:
    assert resolve_runtime("cpu", None, max_host_bytes="64MiB").budget.bytes == 32 << 20
    assert resolve_runtime("cpu", "8MiB", max_host_bytes="64MiB").budget.bytes == 8 << 20
    assert resolve_runtime("cpu", "1GiB", max_host_bytes="64MiB").budget.bytes == 32 << 20
    assert resolve_runtime("cpu", "1GiB").budget.host_bytes is None


def test_a_bound_too_small_says_the_smallest_that_works(scans: dict[str, Path], tmp_path: Path) -> None:
    # the device budget is half the bound on the CPU: too small for a slab of the phantom
    runtime = resolve_runtime("cpu", Budget(host_bytes=1 << 20, host_volume_share=0.01))
    with pytest.raises(BudgetError) as err:
        run_job(scans["tiff-folder"], tmp_path / "a", _spec(), runtime)
    assert "give a --max-host-bytes of at least" in str(err.value)
    needed = err.value.needed
    # a bound that cannot hold one read of planes (two planes of 8 KiB in an eighth of it)
    runtime = resolve_runtime("cpu", Budget(bytes=DEVICE, host_bytes=100_000, host_volume_share=0.01))
    with pytest.raises(BudgetError, match=r"cannot hold one read of this scan's planes.*give at least 128 KiB"):
        run_job(scans["npy"], tmp_path / "b", _spec(), runtime)
    runtime = resolve_runtime("cpu", Budget(host_bytes=needed, host_volume_share=0.01))
    result = run_job(scans["tiff-folder"], tmp_path / "c", _spec(), runtime)  # the bound it named works
    assert result.report["memory"]["out_of_core"] is True


def test_the_cli_flag_and_its_refusal(scans: dict[str, Path], tmp_path: Path) -> None:
    """``--max-host-bytes``: a scan under half the bound is loaded whole; over it, the body outline on data read as
    HU + 1024 is refused with exit 2 and the option that avoids it."""
    args = ["reconstruct", str(scans["npy"]), "--voxel-size", "0.5,0.5,0.5", "--device", "cpu", "--quiet"]
    res = run_cli(*args, "-o", str(tmp_path / "a"), "--max-host-bytes", "512KiB", cwd=tmp_path)
    assert res.returncode == 2 and "--keep-outside-body" in res.stderr, res.stderr
    res = run_cli(*args, "-o", str(tmp_path / "b"), "--max-host-bytes", "512KiB", "--keep-outside-body", cwd=tmp_path)
    assert res.returncode == 2 and "give a --max-host-bytes of at least" in res.stderr, res.stderr
    res = run_cli(*args, "-o", str(tmp_path / "c"), "--max-host-bytes", "1GiB", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    report = json.loads((tmp_path / "c" / "report.json").read_text())
    assert report["memory"]["out_of_core"] is False and report["memory"]["budget_bytes"] == 512 << 20


def test_on_opencl_the_same_model(scans: dict[str, Path], tmp_path: Path) -> None:
    from tests.engine.conftest import opencl_missing

    if opencl_missing():
        pytest.skip(f"OpenCL backend: {opencl_missing()}")
    whole = run_job(scans["npy"], tmp_path / "a", _spec(), resolve_runtime("opencl", Budget(bytes=DEVICE)))
    sliced = run_job(scans["bigtiff"], tmp_path / "b", _spec(), resolve_runtime("opencl", BOUNDED))
    assert sliced.report["memory"]["out_of_core"] and not whole.report["memory"].get("out_of_core")
    assert (tmp_path / "a" / "model.stl").read_bytes() == (tmp_path / "b" / "model.stl").read_bytes()
