"""The device memory budget (``max_device_bytes``, ``engine.budget.Budget``): streamed volume stages, slab-group and
tiled decimation. Paths the budget would not take on this machine are taken by passing budgets that ask for them
(other costs, or a strategy field set), never by patching the modules."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from engine.budget import Budget, Costs, parse_bytes
from engine.data.phantom import bone_phantom
from engine.errors import BudgetError
from engine.params import ReconParams
from engine.job.pipeline import reconstruct
from engine.types import Volume

pytestmark = pytest.mark.both_backends  # device tests run on Warp's CPU and on OpenCL (tests/conftest.py)

MIB = 1 << 20


@pytest.fixture(scope="module")
def phantom() -> Volume:
    return Volume(bone_phantom((64, 128, 128)), (0.5, 0.5, 0.5), units="HU")


@pytest.fixture(scope="module")
def unbounded(phantom):
    return reconstruct(phantom, ReconParams(), device="cpu")


def topology(report):
    m = report["mesh"]
    return m["watertight"], m["manifold"], m["components"], m["euler"]


def test_parse_bytes():
    assert parse_bytes("8GiB") == 8 << 30
    assert parse_bytes("512 MiB") == 512 << 20
    assert parse_bytes("2G") == 2 << 30
    assert parse_bytes("1.5kb") == 1500
    assert parse_bytes(4096) == 4096
    assert parse_bytes(None) is None and parse_bytes("0") is None
    with pytest.raises(ValueError, match="byte count"):
        parse_bytes("lots")
    with pytest.raises(ValueError, match="positive"):
        parse_bytes(-1)


def test_a_budget_is_parsed_once_and_passed_on_as_it_is():
    budget = Budget.of("17MiB")
    assert budget.bytes == 17 * MIB and budget.limited
    assert Budget.of(budget) is budget
    assert Budget.of(None) == Budget() and not Budget().limited and Budget().fits(1 << 62)
    assert budget.beside(MIB).bytes == 16 * MIB and Budget().beside(MIB) == Budget()
    assert budget.fits_decimation(17 * MIB // Costs().decimate) and not budget.fits_decimation(17 * MIB)
    assert Budget(100, costs=Costs(finish=2)).costs.finish_bytes(10) == 10 * 2 + 10 * 20
    assert Budget(100).place("any device", 100, "the work") == ("any device", None)
    with pytest.raises(ValueError, match="group_mode"):
        Budget(group_mode="halves")
    with pytest.raises(ValueError, match="spill_share"):
        Budget(spill_share=0)


@pytest.mark.parametrize("ring", [False, True], ids=["direct", "plane-feed"])
def test_streamed_volume_stages_are_exact(phantom, ring):
    """Without decimation the mesh never leaves the device: slabs of the Gaussian and MC33 give the same mesh,
    uploaded directly or through the plane feed's ring (as on a CUDA device; here a ring shorter than a slab)."""
    params = dataclasses.replace(ReconParams(), decimate=None)
    ref = reconstruct(phantom, params, device="cpu")
    budget = Budget(40 * MIB, feed_ring_bytes=5 * phantom.data[0].nbytes if ring else None)
    got = reconstruct(phantom, params, device="cpu", max_device_bytes=budget)
    stream = got.report["memory"]["stream"]
    assert stream["slabs"] > 1
    if ring:
        assert stream["feed"]["requests"] >= stream["slabs"]
        assert stream["feed"]["longest_request_planes"] > 5  # some longer than the ring
    else:
        assert "feed" not in stream
    np.testing.assert_array_equal(got.mesh.faces, ref.mesh.faces)
    np.testing.assert_array_equal(got.mesh.vertices, ref.mesh.vertices)


def test_decimation_in_slab_groups_keeps_topology_and_target(phantom, unbounded):
    got = reconstruct(phantom, ReconParams(), device="cpu", max_device_bytes=17 * MIB)
    mem = got.report["memory"]
    assert mem["stream"]["groups"] > 1  # the mesh did not fit: decimated in groups of slabs
    assert all(g["pinned"] > 0 for g in mem["stream"]["group_rounds"])
    assert got.report["counts"]["isosurface"] == unbounded.report["counts"]["isosurface"]
    assert topology(got.report) == topology(unbounded.report) == (True, True, 1, 2)
    target = got.report["decimate"]["target_faces"]
    assert target == unbounded.report["decimate"]["target_faces"]
    assert target <= got.report["mesh"]["n_faces"] <= target * 1.02
    assert mem["peak_bytes"] is not None and mem["peak_bytes"] <= mem["budget_bytes"]
    assert mem["peak_bytes"] < unbounded.report["memory"]["peak_bytes"]
    # the surface is the same surface: enclosed volume within 0.1 %
    assert got.report["mesh"]["volume_mm3"] == pytest.approx(unbounded.report["mesh"]["volume_mm3"], rel=1e-3)


def test_too_small_a_budget_names_one_that_works(phantom):
    with pytest.raises(BudgetError, match="give at least") as err:
        reconstruct(phantom, ReconParams(), device="cpu", max_device_bytes=4 * MIB)
    needed = err.value.needed
    assert needed > 4 * MIB
    got = reconstruct(phantom, ReconParams(), device="cpu", max_device_bytes=needed)
    assert got.report["mesh"]["watertight"]


def test_undecimated_model_over_budget_is_a_clear_error():
    """A noisy volume's undecimated surface streams through its slabs but is too large to finish in the budget."""
    from engine.params import IsoParams

    noise = Volume(np.random.default_rng(0).integers(0, 100, (32, 128, 128)).astype(np.uint8), (1.0, 1.0, 1.0))
    params = ReconParams(iso=IsoParams(iso=49.5), body=None, islands=None, decimate=None, smooth=None)
    with pytest.raises(BudgetError, match=r"model .* faces.* give at least") as err:
        reconstruct(noise, params, device="cpu", max_device_bytes=60 * MIB)
    assert err.value.needed > 60 * MIB
    got = reconstruct(noise, params, device="cpu", max_device_bytes=err.value.needed)
    assert got.report["memory"]["peak_bytes"] <= err.value.needed


@pytest.mark.parametrize("rounds", ["device", "host"])
def test_tiled_rounds_pin_shared_vertices_and_keep_topology(rounds):
    """A device mesh decimated in z tiles (budget far under its decimation): same topology, near the target; in
    rounds on the device (each tile split off, decimated and joined there), or on the host where tiles would be too
    small to fit beside the mesh."""
    import warp as wp

    from engine.decimation import decimate_within
    from engine.isosurface import marching_cubes_33
    from engine.surface import mesh_stats_device

    vol = bone_phantom((48, 96, 96)).astype(np.float32)
    v, f = marching_cubes_33(vol, 1024.0 + 300.0, closed=True, device="cpu")
    with wp.ScopedDevice("cpu"):
        pos, faces = wp.array(v, dtype=wp.vec3), wp.array(f, dtype=wp.vec3i)
        before = mesh_stats_device(pos, faces)
        target = len(f) // 5
        # host rounds: tiles would have to hold the whole mesh beside it (they cannot)
        budget = Budget(len(f) * 300 // 4, max_tiles=1 if rounds == "host" else Budget.max_tiles)
        p2, f2, info = decimate_within(pos, faces, target, budget, wp.get_device("cpu"))
        after = mesh_stats_device(p2, f2)
    assert info["tiled"] and len(info["rounds"]) >= 1 and info.get("on", "host") == rounds
    assert len(info["rounds"][0]["tiles"]) >= 2 and all(t["pinned"] > 0 for t in info["rounds"][0]["tiles"])
    assert [before[k] for k in ("watertight", "components", "euler")] == [
        after[k] for k in ("watertight", "components", "euler")
    ]
    assert after["degenerate_faces"] == 0 and after["inconsistent_edges"] == 0
    assert target <= after["n_faces"] <= target * 1.02


def test_pinned_vertices_stay_put():
    import warp as wp

    from engine.decimation.passes import decimate_carrying
    from engine.isosurface import marching_cubes_33

    vol = bone_phantom((32, 64, 64)).astype(np.float32)
    v, f = marching_cubes_33(vol, 1324.0, closed=True, device="cpu")
    lock = (v[:, 0] < np.quantile(v[:, 0], 0.3)).astype(np.int32)  # the lowest 30 % of the vertices
    with wp.ScopedDevice("cpu"):
        res = decimate_carrying(
            wp.array(v, dtype=wp.vec3), wp.array(f, dtype=wp.vec3i), len(f) // 4, locked=wp.array(lock)
        )
        kept, out = res.kept.numpy(), res.pos.numpy()
    assert set(np.flatnonzero(lock)) <= set(kept)  # none removed
    pinned = lock[kept] != 0
    np.testing.assert_array_equal(out[pinned], v[kept[pinned]])  # none moved
    assert len(res.faces) < len(f) * 0.6  # the free part was decimated


@pytest.mark.gpu
def test_cuda_budget_is_measured_from_the_memory_pool(phantom, unbounded):
    got = reconstruct(phantom, ReconParams(), device="cuda", max_device_bytes=17 * MIB)
    mem = got.report["memory"]
    assert mem["measured_by"] == "cuda memory pool high-water mark"
    assert mem["stream"]["groups"] > 1
    assert 0 < mem["peak_bytes"] <= mem["budget_bytes"]
    assert topology(got.report) == topology(unbounded.report)


def test_groups_spilled_to_the_host_join_the_same(phantom, unbounded):
    """Decimated groups held beyond the spill share go to the host: the tiles there join into the same topology."""
    got = reconstruct(phantom, ReconParams(), device="cpu", max_device_bytes=Budget(17 * MIB, spill_share=1e-4))
    assert got.report["memory"]["stream"]["group_timings"]["spill"] > 0
    assert topology(got.report) == topology(unbounded.report)
    target = got.report["decimate"]["target_faces"]
    assert target <= got.report["mesh"]["n_faces"] <= target * 1.02


@pytest.mark.parametrize("where", ["device", "spilled", "host"])
def test_seam_pass_across_group_borders(phantom, unbounded, where):
    """When the decimated groups will not fit one last pass, they go to the ratio on their own and only the faces
    near their borders are decimated again (the seams): on the device where the groups are, on the device again
    where they had to go to the host but fit beside a seam pass, or on the host where they do not."""
    budget = Budget(17 * MIB, group_mode="seams")  # as if the groups' extrapolated size would not fit one last pass
    if where in ("spilled", "host"):
        budget = dataclasses.replace(budget, spill_share=1e-4)
    if where == "host":  # as if the joined groups left no room for a seam pass beside them
        budget = dataclasses.replace(budget, seams_beside=False)
    else:  # as if the joined groups' decimation needed more than the budget
        budget = dataclasses.replace(budget, last_pass=False)
    got = reconstruct(phantom, ReconParams(), device="cpu", max_device_bytes=budget)
    assert got.report["memory"]["stream"]["group_mode"] == "seams"
    seams = got.report["decimate"]["seams"]
    on = "host" if where == "host" else "device"
    seam_faces = seams["seam_faces_in"] if on == "device" else seams["tiles"][0]["faces_in"]
    assert seam_faces < 0.5 * seams["faces_in"]  # only the faces near the borders
    assert seams.get("on", "host") == on
    assert ("uploaded" in got.report["decimate"]) == (where == "spilled")
    assert topology(got.report) == topology(unbounded.report)
    target = got.report["decimate"]["target_faces"]
    assert target <= got.report["mesh"]["n_faces"] <= target * 1.02


def test_write_outputs_within_a_budget_tiles_the_viewing_copies(unbounded, tmp_path):
    """A budget too small for the phone copy's decimation in one piece: it is decimated in tiles, within budget."""
    import json

    from engine.job.outputs import write_outputs
    from engine.params import ExportParams

    params = dataclasses.replace(ReconParams(), export=ExportParams(phone_max_triangles=5000, ar_max_triangles=2000))
    budget = 5 * MIB  # the layout fits (120 B a face), a one-piece decimation (300 B a face) does not
    write_outputs(unbounded, tmp_path, params, device="cpu", max_device_bytes=budget)
    report = json.loads((tmp_path / "report.json").read_text())
    phone = report["exports"]["phone.glb"]
    assert phone["faces"] <= 5000 and phone["topology_preserved"]
    assert report["exports"]["ar.glb"]["faces"] <= 2000
    with pytest.raises(BudgetError, match="laying out"):
        write_outputs(unbounded, tmp_path / "small", params, device="cpu", max_device_bytes=1 * MIB)
    assert not (tmp_path / "small" / "model.stl").exists()


def test_device_seams_in_batches_when_all_at_once_would_not_fit(phantom, unbounded, device):
    """Seams that would not fit beside the mesh all at once are decimated a few borders at a time (here: one
    border per batch), still on the device, each giving up its share of the faces."""
    budget = Budget(
        17 * MIB,
        group_room_share=2 / 3,  # smaller groups, so that there are several borders
        group_mode="seams",
        last_pass=False,  # as if the joined groups' decimation needed more than the budget
        seam_batch_borders=1,  # as if two borders' seams did not fit beside the mesh together
    )
    got = reconstruct(phantom, ReconParams(), device=device, max_device_bytes=budget)
    dec = got.report["decimate"]
    assert dec["borders"] >= 2
    assert dec["seams"]["complete"] and dec["seams"]["on"] == "device"
    assert dec["seams"]["batches"] == dec["borders"]
    assert topology(got.report) == topology(unbounded.report)
    target = dec["target_faces"]
    assert target <= got.report["mesh"]["n_faces"] <= target * 1.02


def on_the_host(n_bytes: int) -> Budget:
    """As on a GPU: stages that cannot fit the budget go to Warp's CPU device (here the device is the CPU too, so
    what is checked is the hand-over, not the memory saved)."""
    return Budget(n_bytes, host_fallback=True)


def test_model_over_the_budget_finishes_on_the_host():
    """The undecimated noise surface above: over the budget to finish, it is finished on the host instead of
    failing, the same model as without a budget."""
    from engine.params import IsoParams

    noise = Volume(np.random.default_rng(0).integers(0, 100, (32, 128, 128)).astype(np.uint8), (1.0, 1.0, 1.0))
    params = ReconParams(iso=IsoParams(iso=49.5), body=None, islands=None, decimate=None, smooth=None)
    got = reconstruct(noise, params, device="cpu", max_device_bytes=on_the_host(60 * MIB))
    assert got.report["finish"]["device"] == "cpu" and "over the budget" in got.report["finish"]["reason"]
    free = reconstruct(noise, params, device="cpu")
    assert "finish" not in free.report
    assert topology(got.report) == topology(free.report)
    np.testing.assert_array_equal(got.mesh.faces, free.mesh.faces)
    np.testing.assert_array_equal(got.mesh.vertices, free.mesh.vertices)


def test_model_over_the_layout_budget_is_laid_out_on_the_host(unbounded, tmp_path):
    """Too large to lay out within the budget: laid out on the host, its viewing copies decimated on the device
    within the whole budget; the files are those of the unbounded run."""
    import json

    from engine.job.outputs import write_outputs
    from engine.params import ExportParams

    params = dataclasses.replace(ReconParams(), export=ExportParams(phone_max_triangles=5000, ar_max_triangles=2000))
    budget = Costs().layout_bytes(len(unbounded.mesh.faces)) - 1  # just under the layout; the copy goes in tiles
    write_outputs(unbounded, tmp_path / "host", params, device="cpu", max_device_bytes=on_the_host(budget))
    write_outputs(unbounded, tmp_path / "free", params, device="cpu")
    report = json.loads((tmp_path / "host" / "report.json").read_text())
    assert report["layout"]["device"] == "cpu" and "over the budget" in report["layout"]["reason"]
    phone = report["exports"]["phone.glb"]
    assert phone["faces"] <= 5000 and phone["topology_preserved"]
    assert report["exports"]["ar.glb"]["faces"] <= 2000
    for name in ("model.stl", "model.glb"):
        assert (tmp_path / "host" / name).read_bytes() == (tmp_path / "free" / name).read_bytes()


def test_a_mesh_too_large_for_the_room_is_tiled_down_before_its_viewing_copies(unbounded):
    """``viewing._take_to``: a print model whose speck removal does not fit the room is first decimated in tiles to
    what fits (every guard kept, no piece dropped), so its copies are made on the device; one whose speck removal
    fits is taken as it is (its decimation, after the specks go, is tiled if it must be)."""
    from engine.decimation.viewing import _take_to
    from engine.surface import mesh_stats_device

    pos, faces = unbounded.device_mesh[:2]
    dev = pos.device
    islands = Costs().islands
    for room in (None, islands * len(faces)):  # the second far under a one-piece decimation
        same = _take_to(pos, faces, 1000, Budget(room), dev)
        assert same[0] is pos and same[1] is faces and same[2]["faces"] == len(faces)
    room = islands * len(faces) // 2  # half of what its speck removal needs
    tpos, tfaces, note = _take_to(pos, faces, 1000, Budget(room), dev)
    assert note["tiled_from_faces"] == len(faces) and note["faces"] == len(tfaces)
    # toward room // Costs.decimate faces (1/15 of them), as far as the guards allow on this speckled mesh
    assert len(tfaces) <= len(faces) // 3
    assert tfaces.device == dev
    stats = mesh_stats_device(tpos, tfaces)
    assert (stats["watertight"], stats["manifold"], stats["components"], stats["euler"]) == topology(unbounded.report)


def test_viewing_copies_of_a_host_mesh_are_made_on_the_gpu(unbounded, device):
    """A print model laid out on the host (past the budget) has its viewing copies made on the job's GPU."""
    if not device.startswith("cuda"):
        pytest.skip("needs a CUDA device: the host and the job's device are one here")
    import warp as wp

    from engine.decimation import viewing_copies

    pos, faces = unbounded.device_mesh[:2]
    host = wp.get_device("cpu")
    hpos, hfaces = wp.clone(pos, device=host), wp.clone(faces, device=host)
    gpu = wp.get_device(device)
    room = (Costs().islands + Costs().mesh) * len(faces) // 2  # too small to take it up as it is
    phone, ar = viewing_copies(hpos, hfaces, [5000, 2000], None, True, room, gpu)
    assert phone[2]["taken_to"]["device"] == str(gpu) and phone[2]["taken_to"]["tiled_from_faces"] == len(faces)
    assert phone[1].device == gpu and ar[1].device == gpu
    assert len(phone[1]) <= 5000 and len(ar[1]) <= 2000
