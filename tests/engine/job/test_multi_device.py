"""One job over several devices (``engine.isosurface.multi``, docs/multi-gpu.md): the device lists, the z split, and
the joined mesh against one device's under the same per-device budget. CI has no GPU: a list naming one device
twice ("cpu,cpu", "opencl:0,opencl:0") runs the whole split, pinning and join, its parts in turn."""

from __future__ import annotations

import dataclasses
import json
import threading

import numpy as np
import pytest

from engine.budget import Budget
from engine.data.phantom import bone_phantom
from engine.device import device_list, is_device_list, resolve_backends
from engine.isosurface.multi import ModeVote, layer_work, split_layers
from engine.job.pipeline import reconstruct
from engine.params import IsoParams, ReconParams
from engine.types import Volume
from tests.engine.cli.test_cli import run_cli
from tests.engine.conftest import opencl_missing

MIB = 1 << 20


@pytest.fixture(scope="module")
def phantom() -> Volume:
    return Volume(bone_phantom((96, 128, 128)), (0.5, 0.5, 0.5), units="HU")


def twice(device: str) -> str:
    """A list naming ``device`` twice: two parts on one device (CI's way to run the split and the join)."""
    name = "opencl:0" if device == "opencl" else device
    return f"{name},{name}"


def shape_of(report: dict) -> tuple:
    m = report["mesh"]
    return m["watertight"], m["manifold"], m["components"], m["euler"]


# ------------------------------------------------------------------------------------------- device lists
def test_a_list_names_its_devices_in_order():
    assert device_list("cpu,cpu") == ["cpu", "cpu"]
    assert device_list(" cuda:0 , cuda:1 ") == ["cuda:0", "cuda:1"]
    assert is_device_list("cuda:0,cuda:1") and is_device_list("cuda:all") and is_device_list(("cpu", "cpu"))
    assert not is_device_list("cuda:1") and not is_device_list("auto")


@pytest.mark.parametrize("bad", ["cpu,,cpu", "cpu,auto", "cpu,gpu:0", "cpu,cuda:all"])
def test_a_malformed_list_says_what_a_list_is(bad):
    with pytest.raises(ValueError, match="list of devices such as 'cuda:0,cuda:1'"):
        device_list(bad)


def test_an_absent_device_in_a_list_is_named():
    with pytest.raises(ValueError, match="device 'cuda:99' of the list 'cpu,cuda:99'"):
        resolve_backends("cpu,cuda:99")


def test_cuda_all_without_a_gpu_says_so():
    import warp as wp

    from engine.device import cuda_available

    if cuda_available():
        assert device_list("cuda:all") == [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]
        return
    with pytest.raises(ValueError, match="'cuda:all': no CUDA device is present"):
        device_list("cuda:all")


def test_a_list_mixing_backends_is_refused_with_the_reason():
    why = opencl_missing()
    if why is not None:
        pytest.skip(f"OpenCL backend: {why}")
    with pytest.raises(ValueError, match=r"mix backends \(opencl, warp\).*not both"):
        resolve_backends("cpu,opencl:0")


def test_one_device_keeps_its_runtime_and_a_list_carries_its_backends():
    from engine.job.runtime import resolve_runtime

    one = resolve_runtime("cpu")
    assert one.devices == () and one.device is one.backend and one.spec == "cpu"
    two = resolve_runtime("cpu,cpu", "64MiB")
    assert two.device == (two.backend, two.backend) and two.spec == "cpu,cpu" and two.requested == "cpu,cpu"
    assert two.budget.bytes == 64 * MIB and "device cpu,cpu ->" in two.describe()


def test_the_cli_takes_a_list_and_refuses_a_bad_one_in_one_line(tmp_path):
    np.save(tmp_path / "ball.npy", bone_phantom((40, 48, 48)))
    out = tmp_path / "out"
    args = ["reconstruct", "ball.npy", "--spacing", "0.5,0.5,0.5", "-o", str(out), "--quiet", "--iso", "1150"]
    bad = run_cli(*args, "--device", "cpu,cuda:99", cwd=tmp_path)
    assert bad.returncode == 2 and "device 'cuda:99' of the list 'cpu,cuda:99'" in bad.stderr
    assert bad.stderr.strip().count("\n") == 0 and not out.exists()
    res = run_cli(*args, "--device", "cpu,cpu", "--max-device-bytes", "8MiB", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["device"]["devices"] == ["cpu", "cpu"]
    assert len(report["memory"]["stream"]["parts"]) == 2 and report["mesh"]["watertight"]


# ------------------------------------------------------------------------------------------- the split
def test_layers_split_into_parts_of_equal_work():
    assert split_layers([1.0] * 9, 3) == [(0, 3), (3, 6), (6, 9)]
    assert split_layers([1, 1, 1, 1, 1, 1, 5, 5], 2) == [(0, 6), (6, 8)]  # the dense end gets fewer layers
    assert split_layers([1.0, 1.0], 3) == [(0, 1), (1, 2)]  # no part without a layer
    assert split_layers([0.0, 0.0, 9.0], 2) == [(0, 2), (2, 3)]


def test_work_follows_the_surface():
    vol = np.zeros((64, 32, 32), np.float32)
    vol[40:60, 8:24, 8:24] = 1.0  # the surface only in the upper half
    work = layer_work(vol, 0.5, 9)
    assert work[:4].sum() < work[5:8].sum() and work.min() > 0
    assert split_layers(work, 2)[0][1] > 4


def test_the_parts_agree_on_the_lowest_parts_finish():
    vote = ModeVote(3)
    got: dict[int, str] = {}
    upper = threading.Thread(target=lambda: got.setdefault(2, vote.mode(2, "seams")))
    upper.start()
    upper.join(0.05)
    assert upper.is_alive()  # part 2 waits for the parts below it
    vote.finish(0)  # part 0 had no surface: no proposal
    got[1] = vote.mode(1, "last pass")
    upper.join()
    assert got == {1: "last pass", 2: "last pass"}


# ------------------------------------------------------------------------------------------- the mesh
@pytest.mark.both_backends
@pytest.mark.parametrize("mode", ["last pass", "seams"])
def test_parts_join_into_the_one_device_mesh(phantom, device, mode):
    """Two and three parts on one device against that device alone, with the same budget: the MC33 mesh is the same
    (faces and vertices, none counted twice at the parts' borders), and the decimated model has the same topology,
    faces within 1 % and the same enclosed volume."""
    budget = Budget(12 * MIB, group_mode=mode)
    if mode == "seams":  # only the faces near the borders get a last pass
        budget = dataclasses.replace(budget, last_pass=False)
    one = reconstruct(phantom, ReconParams(), device=device, max_device_bytes=budget)
    for n in (2, 3):
        spec = ",".join([twice(device).split(",")[0]] * n)
        got = reconstruct(phantom, ReconParams(), device=spec, max_device_bytes=budget)
        stream = got.report["memory"]["stream"]
        assert len(stream["parts"]) == n and stream["group_mode"] == mode
        assert stream["joined_on"] == "device"  # the parts' groups fit beside each other, as one device's do
        assert got.report["counts"]["isosurface"] == one.report["counts"]["isosurface"]
        assert shape_of(got.report) == shape_of(one.report) == (True, True, 1, 2)
        faces, target = got.report["mesh"]["n_faces"], got.report["decimate"]["target_faces"]
        assert target == one.report["decimate"]["target_faces"]
        assert abs(faces - one.report["mesh"]["n_faces"]) <= 0.01 * one.report["mesh"]["n_faces"]
        assert got.report["mesh"]["volume_mm3"] == pytest.approx(one.report["mesh"]["volume_mm3"], rel=1e-3)


@pytest.mark.both_backends
def test_parts_spilled_to_the_host_join_the_same(phantom, device):
    """Each part's groups go to the host as they are decimated (the spill): the join reads them there."""
    budget = Budget(12 * MIB, spill_share=1e-4)
    one = reconstruct(phantom, ReconParams(), device=device, max_device_bytes=budget)
    got = reconstruct(phantom, ReconParams(), device=twice(device), max_device_bytes=budget)
    assert got.report["memory"]["stream"]["joined_on"] == "host"
    assert shape_of(got.report) == shape_of(one.report)
    assert abs(got.report["mesh"]["n_faces"] - one.report["mesh"]["n_faces"]) <= 0.01 * one.report["mesh"]["n_faces"]


def test_a_part_without_surface_joins_the_rest():
    """A part of empty air (the object lies in the top part only): it has no groups, and the mesh is still one
    closed surface, the same as one device's."""
    vol = np.zeros((96, 40, 40), np.float32)
    yy, xx = np.mgrid[:40, :40]
    for z in range(60, 90):
        vol[z] = ((yy - 20) ** 2 + (xx - 20) ** 2 < (8 + (z % 7)) ** 2).astype(np.float32)
    volume = Volume(vol, (1.0, 1.0, 1.0))
    params = ReconParams(gaussian=None, body=None, islands=None, iso=IsoParams(iso=0.5))
    one = reconstruct(volume, params, device="cpu", max_device_bytes=8 * MIB)
    got = reconstruct(volume, params, device="cpu,cpu,cpu", max_device_bytes=8 * MIB)
    assert got.report["memory"]["stream"]["parts"][0]["mc33_faces"] == 0
    assert shape_of(got.report) == shape_of(one.report) == (True, True, 1, 2)


def test_a_tangle_of_many_pieces_and_handles_joins_the_same():
    """Smoothed noise at its median: 15 pieces with hundreds of handles crossing every part's border; four parts
    give one device's MC33 mesh and the same topology (the seams are pinned and matched edge by edge)."""
    from scipy.ndimage import gaussian_filter

    noise = gaussian_filter(np.random.default_rng(1).random((96, 64, 64)).astype(np.float32), 2.0)
    volume = Volume(noise, (1.0, 1.0, 1.0))
    params = ReconParams(gaussian=None, body=None, islands=None, iso=IsoParams(iso=float(np.median(noise))))
    one = reconstruct(volume, params, device="cpu", max_device_bytes=24 * MIB)
    got = reconstruct(volume, params, device="cpu,cpu,cpu,cpu", max_device_bytes=24 * MIB)
    assert len(got.report["memory"]["stream"]["parts"]) == 4
    assert got.report["counts"]["isosurface"] == one.report["counts"]["isosurface"]
    assert shape_of(got.report) == shape_of(one.report) and one.report["mesh"]["components"] > 1
    assert abs(got.report["mesh"]["n_faces"] - one.report["mesh"]["n_faces"]) <= 0.01 * one.report["mesh"]["n_faces"]


@pytest.mark.parametrize("fmt", ["bigtiff", "ome-zarr"])
def test_a_scan_read_slab_by_slab_over_two_parts(tmp_path, fmt):
    """The job path (``run_job``, ``Runtime.device``) under a host memory bound: the scan is read slab by slab by
    both parts, in turns, through the plane feed's ring; the model is one device's, as from the loaded scan."""
    import tifffile

    from engine.job import JobSpec, resolve_runtime, run_job
    from tests.engine.omezarr_factory import write_ome_zarr

    vol = bone_phantom((40, 64, 64), workers=1)
    path = tmp_path / ("scan.tif" if fmt == "bigtiff" else "scan.ome.zarr")
    if fmt == "bigtiff":
        tifffile.imwrite(path, vol, bigtiff=True)
    else:
        write_ome_zarr(path, vol, scale=[500.0] * 3, chunks=(8, 32, 32))
    spec = JobSpec()
    spec = dataclasses.replace(
        spec,
        input=dataclasses.replace(spec.input, spacing_zyx_mm=(0.5, 0.5, 0.5)),
        recon=dataclasses.replace(spec.recon, body=None),
    )
    bound = Budget(bytes=16 * MIB, host_bytes=64 * MIB, host_volume_share=0.001, feed_ring_bytes=5 * 64 * 64 * 2)
    one = run_job(path, tmp_path / "one", spec, resolve_runtime("cpu", bound)).report
    got = run_job(path, tmp_path / "two", spec, resolve_runtime("cpu,cpu", bound)).report
    assert got["memory"]["out_of_core"] is True and got["device"]["devices"] == ["cpu", "cpu"]
    assert all(p["feed"]["requests"] > 0 for p in got["memory"]["stream"]["parts"])
    assert got["counts"]["isosurface"] == one["counts"]["isosurface"]
    assert shape_of(got) == shape_of(one) and got["mesh"]["watertight"]
    assert abs(got["mesh"]["n_faces"] - one["mesh"]["n_faces"]) <= 0.01 * one["mesh"]["n_faces"]


def test_one_device_is_todays_path(phantom):
    """A single device never takes the split: the report has no parts, and the mesh is what it was."""
    got = reconstruct(phantom, ReconParams(), device="cpu", max_device_bytes=12 * MIB)
    assert "parts" not in got.report["memory"]["stream"] and "devices" not in got.report["device"]


@pytest.mark.gpu
def test_two_gpus_give_the_one_gpu_mesh(phantom):
    """On a host of two or more GPUs: the parts on their own devices, in their own threads, joined on the first."""
    import warp as wp

    if wp.get_cuda_device_count() < 2:
        pytest.skip("needs two CUDA devices")
    one = reconstruct(phantom, ReconParams(), device="cuda:0", max_device_bytes=12 * MIB)
    got = reconstruct(phantom, ReconParams(), device="cuda:0,cuda:1", max_device_bytes=12 * MIB)
    parts = got.report["memory"]["stream"]["parts"]
    assert [p["device"] for p in parts] == ["cuda:0", "cuda:1"] and parts[1]["peak_bytes"] <= 12 * MIB
    assert got.report["counts"]["isosurface"] == one.report["counts"]["isosurface"]
    assert shape_of(got.report) == shape_of(one.report) == (True, True, 1, 2)
    assert abs(got.report["mesh"]["n_faces"] - one.report["mesh"]["n_faces"]) <= 0.01 * one.report["mesh"]["n_faces"]


def test_the_parts_threads_never_lean_on_warps_default_device(phantom, monkeypatch):
    """Warp's default device is the process's, not a thread's: parts on two GPUs, each in its own thread, would race
    on it. Every Warp call a part's thread makes names its device (an array's, or the backend's): none asks Warp for
    the default device (``get_device(None)``), here on the whole split, stream, decimation and join (two parts on
one GPU where there is one: the CUDA paths; else on the CPU)."""
    from warp._src import context as wctx

    asked: list[str] = []
    original = wctx.runtime.get_device

    def get_device(ident=None):
        if ident is None and threading.current_thread().name.startswith("bonemesh-part-"):
            import traceback

            asked.append("".join(traceback.format_stack(limit=8)))
        return original(ident)

    from engine.device import cuda_available

    monkeypatch.setattr(wctx.runtime, "get_device", get_device)
    spec = "cuda:0,cuda:0" if cuda_available() else "cpu,cpu"  # on a GPU, the CUDA paths too (pinned rings)
    got = reconstruct(phantom, ReconParams(), device=spec, max_device_bytes=12 * MIB)
    assert len(got.report["memory"]["stream"]["parts"]) == 2
    assert not asked, asked[0]
