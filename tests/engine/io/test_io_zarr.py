"""OME-Zarr inputs (``engine.io.omezarr``): v0.4 on Zarr v2 and v0.5 on Zarr v3, from a folder, a zip and a real S3
store (SeaweedFS), the voxel size and origin from the coordinate transformations, the level picked, the mesh the
same as from the array as .npy, and bad input refused in one line (exit 2 from the CLI).

The fixtures in ``tests/data/ome_zarr`` were written by ome-zarr-py's ``write_image`` (``make_fixtures.py`` there);
the other cases are written with zarr following the specification (``tests/engine/omezarr_factory.py``).
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from engine.data.phantom import bone_phantom
from engine.errors import InputError, NoSpacingError
from engine.io import InputLimits, inspect_input, load_volume
from tests.engine.cli.test_cli import read_stl, run_cli
from tests.engine.omezarr_factory import upload_folder, write_ome_zarr, zip_folder

pytest.importorskip("zarr")

FIXTURES = Path(__file__).resolve().parents[2] / "data" / "ome_zarr"
SHAPE = (16, 32, 40)  # make_fixtures.py's
SPACING = (0.12, 0.1, 0.08)  # its 120, 100, 80 micrometer


@pytest.fixture(scope="module")
def phantom() -> np.ndarray:
    return bone_phantom(SHAPE, workers=1)


def _vol(shape: tuple[int, int, int] = (20, 33, 40), dtype: type = np.uint16) -> np.ndarray:
    return np.random.default_rng(7).integers(0, 4000, size=shape).astype(dtype)


# --- files another project wrote (ome-zarr-py) ---------------------------------------------------------------------


@pytest.mark.parametrize(("name", "version", "zarr_format"), [("phantom_v04", "0.4", 2), ("phantom_v05", "0.5", 3)])
def test_ome_zarr_py_files_read_whole_with_their_voxel_size(
    phantom: np.ndarray, name: str, version: str, zarr_format: int
) -> None:
    vol = load_volume(FIXTURES / f"{name}.ome.zarr")
    assert vol.data.dtype == np.uint16 and vol.data.flags.c_contiguous
    np.testing.assert_array_equal(vol.data, phantom)
    assert vol.spacing_zyx_mm == SPACING and vol.origin_mm == (0.0, 0.0, 0.0)
    assert vol.source == {
        "format": "ome-zarr",
        "container": "folder",
        "ome_version": version,
        "zarr_format": zarr_format,
        "level": "s0",
        "levels": 2,
        "dtype": "uint16",
        "spacing_from": "ome-zarr",
    }


@pytest.mark.parametrize("name", ["phantom_v04", "phantom_v05"])
def test_a_named_level_and_its_translation(name: str) -> None:
    """ome-zarr-py's second level: halved on every axis, its pixel centres shifted by half a full-resolution voxel
    (its translation). The level is named by its path, as an argument or as the path's last part."""
    by_arg = load_volume(FIXTURES / f"{name}.ome.zarr", level="s1")
    by_index = load_volume(FIXTURES / f"{name}.ome.zarr", level=1)
    by_path = load_volume(FIXTURES / f"{name}.ome.zarr" / "s1")
    for vol in (by_arg, by_index, by_path):
        assert vol.data.shape == (8, 16, 20) and vol.source["level"] == "s1"
        assert vol.spacing_zyx_mm == (0.24, 0.2, 0.16)
        np.testing.assert_allclose(vol.origin_mm, (0.04, 0.05, 0.06))  # x, y, z: half a level-0 voxel
    np.testing.assert_array_equal(by_arg.data, by_path.data)


def test_reconstruct_from_zarr_is_the_mesh_of_the_npy(tmp_path: Path, phantom: np.ndarray) -> None:
    """``bonemesh reconstruct`` (the job path) from each OME-Zarr folder and from a zip of one gives the mesh that
    the same array as .npy with the same voxel size gives."""
    np.save(tmp_path / "phantom.npy", phantom)
    zipped = zip_folder(FIXTURES / "phantom_v05.ome.zarr", tmp_path / "phantom_v05.zip")
    runs = {
        "npy": [str(tmp_path / "phantom.npy"), "--voxel-size", ",".join(map(str, SPACING))],
        "v04": [str(FIXTURES / "phantom_v04.ome.zarr")],
        "v05": [str(FIXTURES / "phantom_v05.ome.zarr")],
        "zip": [str(zipped)],
    }
    meshes = {}
    for key, args in runs.items():
        res = run_cli("reconstruct", *args, "-o", str(tmp_path / key), "--device", "cpu", "--quiet", cwd=tmp_path)
        assert res.returncode == 0, res.stderr
        tri, n = read_stl(tmp_path / key / "model.stl")
        assert n > 100
        meshes[key] = tri
        report = json.loads((tmp_path / key / "report.json").read_text())
        assert report["input"]["source"]["format"] == ("npy" if key == "npy" else "ome-zarr")
    for key in ("v04", "v05", "zip"):
        np.testing.assert_array_equal(meshes[key], meshes["npy"], err_msg=key)


# --- the specification's other cases, written with zarr ------------------------------------------------------------


@pytest.mark.parametrize("version", ["0.4", "0.5"])
def test_units_translation_and_singleton_axes(tmp_path: Path, version: str) -> None:
    data = _vol()
    path = write_ome_zarr(
        tmp_path / "scan.ome.zarr",
        data,
        version=version,
        scale=(500.0, 250.0, 125.0),
        unit="nanometer",
        translation=(1000.0, 2000.0, 3000.0),
        extra_axes="tc",
        chunks=(4, 16, 16),
        levels=2,
    )
    vol = load_volume(path)
    np.testing.assert_array_equal(vol.data, data)
    assert vol.spacing_zyx_mm == (0.0005, 0.00025, 0.000125)
    assert vol.origin_mm == (0.003, 0.002, 0.001)  # x, y, z
    level = load_volume(path, level="1")
    np.testing.assert_array_equal(level.data, data[::2, ::2, ::2])
    assert level.spacing_zyx_mm == (0.001, 0.0005, 0.00025)


def test_space_axes_in_another_order(tmp_path: Path) -> None:
    """Axes x, y, z (a writer's choice the specification allows): the volume is still (z, y, x)."""
    import zarr

    data = _vol((12, 20, 24))
    group = zarr.open_group(str(tmp_path / "xyz.ome.zarr"), mode="w", zarr_format=3)
    arr = group.create_array("0", shape=data.shape[::-1], dtype=data.dtype, chunks=(8, 8, 5))
    arr[...] = data.transpose(2, 1, 0)
    axes = [{"name": n, "type": "space", "unit": "micrometer"} for n in "xyz"]
    transforms = [{"type": "scale", "scale": [1.0, 2.0, 3.0]}]
    multiscale = {"axes": axes, "datasets": [{"path": "0", "coordinateTransformations": transforms}]}
    group.attrs.put({"ome": {"version": "0.5", "multiscales": [multiscale]}})
    vol = load_volume(tmp_path / "xyz.ome.zarr")
    np.testing.assert_array_equal(vol.data, data)
    assert vol.data.flags.c_contiguous and vol.spacing_zyx_mm == (0.003, 0.002, 0.001)


def test_sharded_v3_and_progress(tmp_path: Path) -> None:
    data = _vol((30, 20, 24))
    path = write_ome_zarr(tmp_path / "s.ome.zarr", data, scale=(0.1, 0.1, 0.1), unit="millimeter", chunks=(2, 10, 12),
                          shards=(6, 20, 24))  # fmt: skip
    seen: list[float] = []
    vol = load_volume(path, on_progress=seen.append)
    np.testing.assert_array_equal(vol.data, data)
    assert seen and seen[-1] == 1.0 and seen == sorted(seen)


@pytest.mark.parametrize(
    ("dtype", "loaded"),
    [(np.float64, np.float32), (np.int8, np.int16), (np.int32, np.uint16), (">u2", np.uint16), (">i4", np.uint16)],
)
def test_other_sample_types_are_narrowed(tmp_path: Path, dtype: Any, loaded: type) -> None:
    data = _vol((6, 8, 10)).astype(dtype) if dtype != np.int8 else (_vol((6, 8, 10)) % 100).astype(np.int8)
    version = "0.4" if str(dtype).startswith(">") else "0.5"  # big-endian: a Zarr v2 dtype
    path = write_ome_zarr(tmp_path / "t.ome.zarr", data, version=version, scale=(1, 1, 1), unit="mm", chunks=(2, 8, 10))
    vol = load_volume(path)
    assert vol.data.dtype == loaded and vol.data.dtype.isnative
    np.testing.assert_array_equal(vol.data, data.astype(loaded))


def test_allocate_gets_the_volume_and_the_limit_is_checked_first(tmp_path: Path) -> None:
    data = _vol((8, 9, 10))
    path = write_ome_zarr(tmp_path / "a.ome.zarr", data, scale=(1, 1, 1), unit="mm")
    made: list[tuple[tuple[int, ...], np.dtype]] = []

    def allocate(shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
        made.append((shape, dtype))
        return np.empty(shape, dtype)

    vol = load_volume(path, allocate=allocate)
    assert made == [((8, 9, 10), np.dtype(np.uint16))]
    np.testing.assert_array_equal(vol.data, data)
    with pytest.raises(InputError, match=r"720 voxels.*limit of 100"):
        load_volume(path, limits=InputLimits(max_voxels=100), allocate=allocate)
    assert len(made) == 1


def test_a_zip_of_the_folder_or_of_its_contents(tmp_path: Path) -> None:
    data = _vol()
    path = write_ome_zarr(tmp_path / "scan.ome.zarr", data, version="0.4", scale=(2, 1, 1), unit="micrometer")
    for archive in (zip_folder(path, tmp_path / "top.zip"), zip_folder(path, tmp_path / "flat.zip", top=False)):
        vol = load_volume(archive)
        np.testing.assert_array_equal(vol.data, data)
        assert vol.source["container"] == "zip" and vol.spacing_zyx_mm == (0.002, 0.001, 0.001)
        assert inspect_input(archive).kind == "ome-zarr (zip)"


def test_a_folder_holding_the_image_and_a_bioformats2raw_layout(tmp_path: Path) -> None:
    data = _vol((6, 8, 10))
    write_ome_zarr(tmp_path / "upload" / "scan.ome.zarr", data, scale=(1, 1, 1), unit="mm", chunks=(1, 4, 5))
    (tmp_path / "upload" / "notes.txt").write_text("scanned on Tuesday")
    # the image's 24 chunk files are not listed one by one: the folder's member limit is not spent on them
    vol = load_volume(tmp_path / "upload", limits=InputLimits(max_members=5))
    np.testing.assert_array_equal(vol.data, data)
    assert vol.source["container"] == "folder"
    import zarr

    root = zarr.open_group(str(tmp_path / "b2r.zarr"), mode="w", zarr_format=2)
    root.attrs.put({"bioformats2raw.layout": 3})
    write_ome_zarr(tmp_path / "b2r.zarr" / "0", data, version="0.4", scale=(1, 1, 1), unit="mm")
    np.testing.assert_array_equal(load_volume(tmp_path / "b2r.zarr").data, data)


def test_the_callers_voxel_size_wins_and_fills_in_missing_units(tmp_path: Path) -> None:
    data = _vol((6, 8, 10))
    unitless = write_ome_zarr(tmp_path / "u.ome.zarr", data, scale=(2.0, 0.5, 0.5), unit=None)
    with pytest.raises(NoSpacingError, match=r"scale \(z 2 \(no unit\), y 0.5 \(no unit\).*voxel size in mm"):
        load_volume(unitless)
    attrs = {"multiscales": [{"version": "0.3", "axes": ["z", "y", "x"], "datasets": [{"path": "0"}]}]}
    unscaled = write_ome_zarr(tmp_path / "v03.ome.zarr", data, version="0.4", attrs=attrs)
    with pytest.raises(NoSpacingError, match=r"give no scale \(coordinateTransformations\); give the voxel size"):
        load_volume(unscaled)
    np.testing.assert_array_equal(load_volume(unscaled, spacing_zyx_mm=(1, 1, 1)).data, data)
    vol = load_volume(unitless, spacing_zyx_mm=(0.2, 0.05, 0.05))
    assert vol.spacing_zyx_mm == (0.2, 0.05, 0.05) and vol.source["spacing_from"] == "call"


# --- bad input: one clear line ---------------------------------------------------------------------------------------


def _broken(tmp_path: Path, case: str) -> Path:
    data = _vol((6, 8, 10))
    path = tmp_path / f"{case}.ome.zarr"
    if case == "no-multiscales":
        return write_ome_zarr(path, data, attrs={"name": "just a group"})
    if case == "unknown-unit":
        return write_ome_zarr(path, data, unit="furlong")
    if case == "time-unit":
        return write_ome_zarr(path, data, unit="second")
    if case == "channels":
        write_ome_zarr(path, data, extra_axes="c")
        import zarr

        z = zarr.open_group(str(path), mode="r+")
        z.create_array("0", shape=(3, *data.shape), dtype=data.dtype, overwrite=True)
        return path
    if case == "no-datasets":
        return write_ome_zarr(path, data, attrs={"ome": {"version": "0.5", "multiscales": [{"axes": []}]}})
    if case == "bare-array":
        import zarr

        zarr.create_array(str(path), shape=data.shape, dtype=data.dtype)
        return path
    raise AssertionError(case)


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("no-multiscales", "is a Zarr group but not an OME-Zarr image: no multiscales metadata"),
        ("unknown-unit", "axis 'z' has unit 'furlong', not a length bonemesh knows"),
        ("time-unit", "axis 'z' has unit 'second', not a length"),
        ("channels", "it holds 3 channels \\(axis 'c'\\); bonemesh meshes one 3-D volume"),
        ("no-datasets", "lists no datasets"),
        ("bare-array", "is a bare Zarr array, not an OME-Zarr image"),
    ],
)
def test_bad_zarr_is_refused_in_one_line(tmp_path: Path, case: str, message: str) -> None:
    path = _broken(tmp_path, case)
    with pytest.raises(InputError, match=message) as info:
        load_volume(path)
    assert "\n" not in str(info.value)


def test_a_missing_level_lists_the_levels(tmp_path: Path) -> None:
    with pytest.raises(
        InputError, match=r"has no level 's7'; its levels are 0: 's0' \(16x32x40\), 1: 's1' \(8x16x20\)"
    ):
        load_volume(FIXTURES / "phantom_v05.ome.zarr", level="s7")
    with pytest.raises(InputError, match="has no level 2"):
        load_volume(FIXTURES / "phantom_v04.ome.zarr", level=2)
    with pytest.raises(InputError, match=r"level='s1' was given, but .* is not an OME-Zarr image"):
        load_volume(FIXTURES / "make_fixtures.py", level="s1")


def test_a_listed_level_whose_array_is_gone(tmp_path: Path) -> None:
    path = tmp_path / "copy.ome.zarr"
    zipfile.ZipFile(zip_folder(FIXTURES / "phantom_v05.ome.zarr", tmp_path / "c.zip", top=False)).extractall(path)
    (path / "s1").rename(tmp_path / "elsewhere")
    assert load_volume(path).data.shape == SHAPE
    with pytest.raises(InputError, match=r"copy\.ome\.zarr: level 's1' cannot be opened"):
        load_volume(path, level=1)


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("unknown-unit", "axis 'z' has unit 'furlong', not a length bonemesh knows"),
        ("no-multiscales", "is a Zarr group but not an OME-Zarr image"),
        ("missing-level", "phantom_v05.ome.zarr/s9 does not exist"),
    ],
)
def test_cli_exits_2_with_one_line(tmp_path: Path, case: str, message: str) -> None:
    path = FIXTURES / "phantom_v05.ome.zarr" / "s9" if case == "missing-level" else _broken(tmp_path, case)
    res = run_cli("reconstruct", str(path), "-o", str(tmp_path / "out"), "--device", "cpu", cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], res.stderr
    assert not (tmp_path / "out").exists()


# --- S3: a real SeaweedFS ---------------------------------------------------------------------------------------------


@pytest.fixture
def seaweed(seaweed_server: object) -> object:
    """The session's SeaweedFS (tests/conftest.py), for readers that need obstore."""
    pytest.importorskip("obstore")
    return seaweed_server


def _s3_env(monkeypatch: pytest.MonkeyPatch, server: object, bucket: str) -> dict[str, str]:
    env = {k: v for k, v in server.env(bucket).items() if k != "BONEMESH_STORAGE_URL"}  # type: ignore[attr-defined]
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    monkeypatch.delenv("AWS_REGION", raising=False)
    return env


def test_s3_reads_the_image_and_a_level(
    tmp_path: Path, seaweed: object, monkeypatch: pytest.MonkeyPatch, phantom: np.ndarray
) -> None:
    bucket = seaweed.make_bucket()  # type: ignore[attr-defined]
    client = seaweed.client()  # type: ignore[attr-defined]
    _s3_env(monkeypatch, seaweed, bucket)
    url = upload_folder(client, FIXTURES / "phantom_v05.ome.zarr", bucket, "scans/phantom.ome.zarr")
    vol = load_volume(url)
    np.testing.assert_array_equal(vol.data, phantom)
    assert vol.spacing_zyx_mm == SPACING and vol.source["container"] == "s3"
    assert load_volume(url + "/s1").data.shape == (8, 16, 20)
    v04 = upload_folder(client, FIXTURES / "phantom_v04.ome.zarr", bucket, "v04.ome.zarr")
    np.testing.assert_array_equal(load_volume(v04, level=0).data, phantom)
    with pytest.raises(InputError, match=rf"s3://{bucket}/nothing.ome.zarr \(S3 store at http.*holds no Zarr image"):
        load_volume(f"s3://{bucket}/nothing.ome.zarr")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "not-the-key")
    with pytest.raises(InputError, match=r"cannot be reached or read: PermissionDenied"):
        load_volume(url)


def test_s3_through_the_cli_is_the_mesh_of_the_folder(
    tmp_path: Path, seaweed: object, monkeypatch: pytest.MonkeyPatch
) -> None:
    bucket = seaweed.make_bucket()  # type: ignore[attr-defined]
    url = upload_folder(seaweed.client(), FIXTURES / "phantom_v04.ome.zarr", bucket, "p.ome.zarr")  # type: ignore[attr-defined]
    env = {k: v for k, v in seaweed.env(bucket).items() if k != "BONEMESH_STORAGE_URL"}  # type: ignore[attr-defined]
    for k, v in env.items():  # run_cli passes this process's environment on
        monkeypatch.setenv(k, v)
    res = run_cli("reconstruct", url, "-o", str(tmp_path / "s3"), "--device", "cpu", "--quiet", cwd=tmp_path)
    local = run_cli("reconstruct", str(FIXTURES / "phantom_v04.ome.zarr"), "-o", str(tmp_path / "local"),
                    "--device", "cpu", "--quiet", cwd=tmp_path)  # fmt: skip
    assert res.returncode == 0 and local.returncode == 0, res.stderr + local.stderr
    np.testing.assert_array_equal(
        read_stl(tmp_path / "s3" / "model.stl")[0], read_stl(tmp_path / "local" / "model.stl")[0]
    )


def test_an_unreachable_store_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("obstore")
    monkeypatch.setenv("BONEMESH_S3_ENDPOINT_URL", "http://127.0.0.1:9")
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "k")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "s")
    with pytest.raises(InputError, match=r"s3://b/scan.ome.zarr \(S3 store at http://127.0.0.1:9\) cannot be reached"):
        load_volume("s3://b/scan.ome.zarr")


# --- a level by name for every way in (issue 46: the API's zarr_level, the CLI's --zarr-level) ---------------------


def test_the_cli_reads_the_level_it_is_given(tmp_path: Path) -> None:
    """``--zarr-level`` by path and by index reads ome-zarr-py's second level (report and mesh the same either way);
    given for an input of another kind, the command exits 2 with one line."""
    zipped = zip_folder(FIXTURES / "phantom_v05.ome.zarr", tmp_path / "phantom_v05.zip")
    meshes = []
    for level in ("s1", "1"):
        out = tmp_path / f"level-{level}"
        res = run_cli("reconstruct", str(zipped), "--zarr-level", level, "-o", str(out), "--device", "cpu", "--quiet",
                      "--iso", "1100", cwd=tmp_path)  # fmt: skip
        assert res.returncode == 0, res.stderr
        source = json.loads((out / "report.json").read_text())["input"]
        assert source["source"]["level"] == "s1" and source["shape_zyx"] == [8, 16, 20]
        meshes.append(read_stl(out / "model.stl")[0])
    np.testing.assert_array_equal(meshes[0], meshes[1])
    np.save(tmp_path / "v.npy", _vol())
    res = run_cli("reconstruct", str(tmp_path / "v.npy"), "--voxel-size", "1,1,1", "--zarr-level", "1", "-o",
                  str(tmp_path / "npy"), "--device", "cpu", "--quiet", cwd=tmp_path)  # fmt: skip
    assert res.returncode == 2 and "level='1' was given, but v.npy is not an OME-Zarr image" in res.stderr
    res = run_cli("reconstruct", str(zipped), "--zarr-level", "s9", "-o", str(tmp_path / "s9"), "--device", "cpu",
                  "--quiet", cwd=tmp_path)  # fmt: skip
    assert res.returncode == 2 and "no level 's9'; its levels are" in res.stderr


def test_a_job_reads_its_zarr_level(tmp_path: Path) -> None:
    """The job path (``run_job``: what the worker runs) reads the level its spec names; an unknown level fails the
    job in words, naming the levels there are."""
    from engine.errors import InputError as JobInputError
    from engine.job import JobSpec, run_job
    from engine.job.runtime import resolve_runtime
    from engine.job.spec import InputSpec
    from engine.params import IsoParams, ReconParams

    zipped = zip_folder(FIXTURES / "phantom_v04.ome.zarr", tmp_path / "phantom_v04.zip")
    spec = JobSpec(recon=ReconParams(iso=IsoParams(iso=1100.0)), input=InputSpec(zarr_level="s1"))
    result = run_job(zipped, tmp_path / "out", spec, resolve_runtime("cpu"))
    assert result.report["input"]["source"]["level"] == "s1"
    assert result.report["input"]["shape_zyx"] == [8, 16, 20]
    with pytest.raises(JobInputError, match="no level 's7'; its levels are"):
        run_job(zipped, tmp_path / "s7", JobSpec(input=InputSpec(zarr_level="s7")), resolve_runtime("cpu"))
