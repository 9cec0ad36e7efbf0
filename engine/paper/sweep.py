"""The paper's parameter sweep (its Tables 1 and 2) on one scan: ``run_sweep`` (the command ``bonemesh sweep`` is
parsed in ``engine.cli.sweep``; this library never imports the CLI).

    bonemesh sweep INPUT --spacing Z,Y,X (--iso V | --preset bone --hu-offset 1024) -o OUTDIR
                   [--reductions 0.2,0.3,...] [--iterations 1,5,...] [--repeats 3] [--slices 64] [--points 200000]
                   [--crop Z0:Z1,Y0:Y1,X0:X1] [--stride N] [--no-mc33] [--full-runs] [--resume] [--device ...]
    bonemesh sweep --demo -o OUTDIR            (bundled headsq CT at level 1150)
    bonemesh sweep --phantom 952,1024,1024 -o OUTDIR   (engine.data.phantom)

Rows (Table 1): **MC33**, scikit-image's Lewiner marching cubes on the CPU without enhancements (the volume is
padded by one sample below the level so its surface is closed too); **MC33GPU**, this engine's MC33 without
enhancements (no Gaussian, decimation or smoothing); **GMC33GPU** (ours, not in the paper), the Gaussian-smoothed
volume's MC33 surface before decimation, which is also the reference of the distances; **EMC33GPU** for every
reduction x iterations pair (Gaussian, MC33, decimation to the reduction factor, ``iterations`` surface-preserving
Laplacian steps). "GPU" is the paper's name: the rows run on the ``--device`` given, CPU included. Columns: the
paper's (RMSE %, SSIM %, reconstruct s, rendering s, faces, vertices) and ours (Dice, distances to the
undecimated surface, mesh quality); see :mod:`engine.paper.metrics` and ``docs/metrics.md``.

Times: the median of ``repeats`` runs after one warm-up on a thin slab. *Reconstruct* is the sum of the pipeline's
stage times (upload to normals; loading and writing files excluded, as in the paper); *rendering* is our stand-in
for the paper's: encoding the GLB, writing it, reading it back and decoding its arrays. By default an EMC33GPU row's
time is composed: the pipeline without smoothing runs once per reduction (its median), and the smoothing and
normal stages are timed per iteration count on that decimated mesh (the stages are deterministic, so the meshes
are those of full runs); ``--full-runs`` runs the whole pipeline for every pair instead.

Table 2: the paper's enhancement score ``0.6 * accuracy + 0.3 * size + 0.1 * time`` of each pair against the
MC33GPU row (see :func:`engine.paper.sweep_report.enhancement_score`). The tables, CSV files and plots are written by
:mod:`engine.paper.sweep_report`.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from engine.errors import InputError
from engine.paper.sweep_report import json_default, write_tables
from engine.types import Volume

DEFAULT_REDUCTIONS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
DEFAULT_ITERATIONS = (1, 5, 10, 25, 50)
Log = Callable[[str], None]


@dataclass(frozen=True)
class SweepConfig:
    """What the sweep runs.

    Args:
        reductions: decimation reduction factors (fraction of faces kept), each in (0, 1].
        iterations: Laplacian smoothing iteration counts, each >= 1.
        repeats: timed runs per row (the median is reported).
        max_slices: slices compared for RMSE / SSIM / Dice, evenly spread; None: all.
        n_points: surface samples per mesh for the distances.
        seed: sampling seed.
        mc33_reference: run the scikit-image (Lewiner) MC33 row.
        full_runs: time the whole pipeline for every pair instead of composing stage times.
        angle_deg: smoothing threshold angle.
    """

    reductions: tuple[float, ...] = DEFAULT_REDUCTIONS
    iterations: tuple[int, ...] = DEFAULT_ITERATIONS
    repeats: int = 3
    max_slices: int | None = 64
    n_points: int = 200_000
    seed: int = 0
    mc33_reference: bool = True
    full_runs: bool = False
    angle_deg: float = 0.5

    def __post_init__(self) -> None:
        from engine.params import is_reduction

        if not self.reductions or not all(is_reduction(r) for r in self.reductions):
            raise ValueError(f"Expected reduction factors in (0, 1], got {self.reductions}")
        if not self.iterations or not all(i >= 1 for i in self.iterations):
            raise ValueError(f"Expected iteration counts >= 1, got {self.iterations}")
        if self.repeats < 1 or self.n_points < 1 or (self.max_slices is not None and self.max_slices < 1):
            raise ValueError(
                f"Expected repeats, points and slices >= 1, got {self.repeats}, {self.n_points}, {self.max_slices}"
            )


def rendering_seconds(verts: np.ndarray, faces: np.ndarray, normals: np.ndarray | None, folder: Path) -> float:
    """Our stand-in for the paper's rendering time: encode the GLB, write it, read it back and decode it."""
    from engine.export import to_glb
    from engine.export.glb import read_glb

    path = folder / ".sweep-render.glb"
    t0 = time.perf_counter()
    path.write_bytes(to_glb(verts, faces, normals))
    pos, _, idx = read_glb(path.read_bytes())
    seconds = time.perf_counter() - t0
    path.unlink()
    if len(pos) != len(verts) or len(idx) != len(faces):
        raise RuntimeError("the GLB read back does not hold the mesh that was written")
    return seconds


def lewiner_mc33(volume: npt.NDArray[Any], level: float, spacing: tuple[float, float, float]) -> tuple[Any, ...]:
    """scikit-image's Lewiner MC33 of the volume padded by one sample below the level (a closed surface).

    Returns:
        (vertices (V, 3) float32 (z, y, x) mm from the first sample, faces (F, 3) int32 outward, normals).
    """
    from skimage.measure import marching_cubes

    low = min(float(volume.min()), level) - max(1.0, abs(level))
    padded = np.pad(volume.astype(np.float32), 1, constant_values=np.float32(low))
    v, f, n, _ = marching_cubes(padded, level, spacing=spacing, method="lewiner")
    v = (v - np.asarray(spacing, np.float32)).astype(np.float32)
    f = f.astype(np.int32)
    from engine.paper.metrics import volume_area

    if volume_area(v, f)[0] < 0:  # make the faces outward in the engine's (x, y, z) convention
        f = f[:, ::-1].copy()
    return v, f, n.astype(np.float32)


def _median(values: list[float]) -> float:
    return float(statistics.median(values))


class _Sweep:
    """One sweep: the volume, its level, the reference surface, and the rows measured so far."""

    def __init__(self, volume: Volume, level: float, config: SweepConfig, device: str, outdir: Path, log: Log):
        from engine.device import resolve_device

        self.volume, self.level, self.cfg, self.device, self.out, self.log = volume, level, config, device, outdir, log
        self.dev = resolve_device(device)
        self.spacing = tuple(float(s) for s in volume.spacing_zyx_mm)

    def params(self, enhanced: bool, reduction: float | None = None, iterations: int | None = None) -> Any:
        from engine.params import DecimateParams, GaussianParams, IsoParams, ReconParams, SmoothParams

        return ReconParams(  # the paper's rows: every piece kept (no body mask, no speck removal)
            iso=IsoParams(iso=self.level, closed=True),
            islands=None,
            body=None,
            gaussian=GaussianParams() if enhanced else None,
            decimate=DecimateParams(reduction=reduction) if reduction is not None else None,
            smooth=SmoothParams(iterations=iterations, angle_deg=self.cfg.angle_deg) if iterations else None,
        )

    def reconstruct(self, params: Any) -> tuple[Any, list[float]]:
        from engine.job.pipeline import reconstruct

        runs, recon = [], None
        for _ in range(self.cfg.repeats):
            recon = reconstruct(self.volume, params, device=self.device)
            runs.append(float(sum(recon.report["stage_seconds"].values())))
        return recon, runs

    def warm_up(self) -> None:
        """Compile and load every kernel on a thin slab, so that no timed run pays for it."""
        from engine.job.pipeline import reconstruct
        from engine.paper.metrics import SurfaceQuery

        nz = self.volume.data.shape[0]
        lo = max(0, nz // 2 - 8)
        slab = dataclasses.replace(self.volume, data=self.volume.data[lo : lo + 16])
        try:
            recon = reconstruct(slab, self.params(True, 0.5, 1), device=self.device)
            SurfaceQuery(recon.mesh.vertices, recon.mesh.faces, self.device).distances(recon.mesh.vertices[:4])
        except InputError:  # no surface in the slab: the kernels compile on the first timed run instead
            self.log("warm-up slab has no surface; the first timed run includes kernel loading")

    def reference(self) -> None:
        """The undecimated surface of the enhanced pipeline (Gaussian + MC33): distances and changes refer to it."""
        from engine.paper.metrics import DistanceReference

        recon, _ = self.reconstruct_once(self.params(True))
        self.ref_stats = recon.report["mesh"]
        self.ref = DistanceReference(
            recon.mesh.vertices, recon.mesh.faces, n_points=self.cfg.n_points, seed=self.cfg.seed, device=self.device
        )

    def reconstruct_once(self, params: Any) -> tuple[Any, float]:
        from engine.job.pipeline import reconstruct

        recon = reconstruct(self.volume, params, device=self.device)
        return recon, float(sum(recon.report["stage_seconds"].values()))

    def evaluate(
        self, key: dict[str, Any], verts: np.ndarray, faces: np.ndarray, normals: Any, stats: dict[str, Any]
    ) -> dict[str, Any]:
        from engine.paper.metrics import mesh_quality, slice_similarity

        t0 = time.perf_counter()
        sim = slice_similarity(verts, faces, self.volume.data, self.level, self.spacing, max_slices=self.cfg.max_slices)
        dist = self.ref.compare(verts, faces)
        quality = mesh_quality(verts, faces, stats=stats, reference_stats=self.ref_stats)
        render = [rendering_seconds(verts, faces, normals, self.out) for _ in range(self.cfg.repeats)]
        row = {
            **key,
            "rmse_pct": sim["rmse_pct"],
            "ssim_pct": sim["ssim_pct"],
            "rendering_s": _median(render),
            "faces": len(faces),
            "vertices": len(verts),
            "dice": sim["dice"],
            "mean_mm": dist["mean_mm"],
            "p95_mm": dist["p95_mm"],
            "hausdorff_mm": dist["hausdorff_mm"],
            **{k: quality[k] for k in ("watertight", "manifold", "components", "euler")},
            "min_angle_p5_deg": quality["min_angle_deg"]["p5"],
            "below_10deg": quality["below_10deg"],
            "volume_change_pct": quality["volume_change_pct"],
            "area_change_pct": quality["area_change_pct"],
            "slices_compared": len(sim["slices"]),
            "rendering_s_all": render,
            "distances": {"to_reference": dist["to_reference"], "from_reference": dist["from_reference"]},
            "metrics_s": time.perf_counter() - t0,
        }
        self.log(
            f"  {row['method']:<8} R={row['reduction']} it={row['iterations']}: RMSE {row['rmse_pct']:.2f} % SSIM "
            f"{row['ssim_pct']:.2f} % Dice {row['dice']:.4f}, {row['reconstruct_s']:.3f} s + {row['rendering_s']:.3f}"
            f" s, {row['faces']:,} faces, mean {row['mean_mm']:.4f} mm, Hausdorff {row['hausdorff_mm']:.3f} mm"
        )
        return row

    def rows(self, done: set[tuple[Any, ...]]) -> Any:
        """Yield the rows not in ``done`` (keys ``(method, reduction, iterations)``), measuring each."""
        from engine.paper.metrics import volume_area
        from engine.surface.meshcheck import mesh_stats
        from engine.surface.normals import vertex_normals
        from engine.surface.smooth import smooth_mesh

        if self.cfg.mc33_reference and ("MC33", None, None) not in done:
            runs, res = [], None
            for _ in range(self.cfg.repeats):
                t0 = time.perf_counter()
                res = lewiner_mc33(self.volume.data, self.level, self.spacing)  # type: ignore[arg-type]
                runs.append(time.perf_counter() - t0)
            v, f, n = res  # type: ignore[misc]
            key = {"method": "MC33", "reduction": None, "iterations": None, "reconstruct_s": _median(runs)}
            yield self.evaluate({**key, "reconstruct_s_all": runs}, v, f, n, mesh_stats(v, f))
        if ("MC33GPU", None, None) not in done:
            recon, runs = self.reconstruct(self.params(False))
            m = recon.mesh
            key = {"method": "MC33GPU", "reduction": None, "iterations": None, "reconstruct_s": _median(runs)}
            yield self.evaluate(
                {**key, "reconstruct_s_all": runs}, m.vertices, m.faces, m.normals, recon.report["mesh"]
            )
        if ("GMC33GPU", None, None) not in done:  # Gaussian + MC33: the effect of the volume smoothing alone
            recon, runs = self.reconstruct(self.params(True))
            m = recon.mesh
            key = {"method": "GMC33GPU", "reduction": None, "iterations": None, "reconstruct_s": _median(runs)}
            yield self.evaluate(
                {**key, "reconstruct_s_all": runs}, m.vertices, m.faces, m.normals, recon.report["mesh"]
            )
        for r in self.cfg.reductions:
            todo = [i for i in self.cfg.iterations if ("EMC33GPU", r, i) not in done]
            if not todo:
                continue
            if self.cfg.full_runs:
                for i in todo:
                    recon, runs = self.reconstruct(self.params(True, r, i))
                    m = recon.mesh
                    key = {"method": "EMC33GPU", "reduction": r, "iterations": i, "reconstruct_s": _median(runs)}
                    yield self.evaluate(
                        {**key, "reconstruct_s_all": runs}, m.vertices, m.faces, m.normals, recon.report["mesh"]
                    )
                continue
            base, runs = self.reconstruct(self.params(True, r, None))
            before = [t - base.report["stage_seconds"]["normals"] for t in runs]  # upload .. decimate
            topo = base.report["mesh"]
            v_dec, f_dec = base.mesh.vertices, base.mesh.faces
            for i in todo:
                tail, verts, normals = [], v_dec, base.mesh.normals
                for _ in range(self.cfg.repeats):
                    t0 = time.perf_counter()
                    verts, _ = smooth_mesh(v_dec, f_dec, self.params(True, r, i).smooth, self.dev)
                    normals = vertex_normals(verts, f_dec, self.dev)
                    tail.append(time.perf_counter() - t0)
                vol, area = volume_area(verts, f_dec)
                stats = {**topo, "volume_mm3": vol, "area_mm2": area}
                total = [_median(before) + t for t in tail]
                key = {"method": "EMC33GPU", "reduction": r, "iterations": i, "reconstruct_s": _median(total)}
                yield self.evaluate({**key, "reconstruct_s_all": total}, verts, f_dec, normals, stats)


def _row_key(row: dict[str, Any]) -> tuple[Any, ...]:
    return (row["method"], row["reduction"], row["iterations"])


def run_sweep(
    volume: Volume,
    level: float,
    outdir: str | Path,
    config: SweepConfig | None = None,
    *,
    device: str = "auto",
    resume: bool = False,
    meta: dict[str, Any] | None = None,
    log: Log | None = None,
) -> list[dict[str, Any]]:
    """Run the sweep on a volume and write its tables and plots into ``outdir``.

    Args:
        volume: the scan (after any crop); ground truth and meshes refer to it.
        level: iso level in the volume's units.
        outdir: output folder: ``meta.json``, ``rows.jsonl`` (one row per line, appended as measured),
            ``table1.csv``, ``table2.csv``, ``tables.md``, ``accuracy_vs_faces.png``, ``time_vs_iterations.png``
            (the tables and plots are rewritten after every row).
        config: the grid and measurement settings.
        device: "auto", "cpu", "cuda" or "cuda:N".
        resume: keep the rows already in ``outdir/rows.jsonl`` (same input) and measure only the missing ones.
        meta: extra facts for ``meta.json`` (e.g. the command line).
        log: progress lines (default: stderr).

    Returns:
        The rows of Table 1 (dicts; keys as in ``table1.csv``).

    Raises:
        InputError: no surface at the level, or ``resume`` on an outdir of another input.
    """
    from engine.job.pipeline import _versions

    cfg = config or SweepConfig()
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    say = log or (lambda s: print(s, file=sys.stderr, flush=True))  # noqa: T201 - progress
    info = {
        "input": {
            "shape_zyx": list(volume.data.shape),
            "spacing_zyx_mm": list(volume.spacing_zyx_mm),
            "dtype": str(volume.data.dtype),
            "level": level,
            "source": volume.source,
        },
        "config": dataclasses.asdict(cfg),
        "device_spec": device,
        "timing": f"median of {cfg.repeats} run(s) after a warm-up; "
        + (
            "full pipeline per pair"
            if cfg.full_runs
            else "EMC33GPU rows composed per reduction (see engine.paper.sweep)"
        ),
        "baseline": "MC33GPU",
        **(meta or {}),
    }
    rows_path = out / "rows.jsonl"
    rows: list[dict[str, Any]] = []
    if resume and rows_path.exists():
        old = json.loads((out / "meta.json").read_text())
        if old.get("input", {}).get("shape_zyx") != info["input"]["shape_zyx"] or old["input"]["level"] != level:
            raise InputError(f"--resume: {out} holds a sweep of another input ({old.get('input')})")
        rows = [json.loads(line) for line in rows_path.read_text().splitlines() if line.strip()]
    else:
        rows_path.write_text("")
    sw = _Sweep(volume, level, cfg, device, out, say)
    info["device"] = str(sw.dev)
    info["device_name"] = getattr(sw.dev, "name", str(sw.dev))
    info["versions"] = _versions()
    (out / "meta.json").write_text(json.dumps(info, indent=2, default=json_default) + "\n")
    say(f"[sweep] {volume.data.shape} at level {level:g} on {sw.dev}: warm-up and reference surface")
    sw.warm_up()
    sw.reference()
    for row in sw.rows({_row_key(r) for r in rows}):
        rows.append(row)
        with rows_path.open("a") as fh:
            fh.write(json.dumps(row, default=json_default) + "\n")
        write_tables(rows, out, info)  # after every row: a run stopped at a time limit keeps its tables
    if rows:
        write_tables(rows, out, info)
    return rows
