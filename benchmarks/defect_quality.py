"""Defect template quality (issue 31): synthetic one-sided defects cut from the healthy real skulls, the intact skulls,
defects across the midline, and the cranium's real defect.

    python -m benchmarks.defect_quality [--device cpu|cuda:0] [--scans headsq,head_phantom,cranium]
                                        [--sizes 20,30,40] [--out benchmarks/results/defect_quality_cpu.json]

For each healthy skull (headsq, bundled; the head phantom from ../shared/data): the intact scan (expected: "no
defect"), then round trephinations (``engine.defect.synthetic.cut_defect``) of several diameters at several places
on both sides, and defects across the midline (expected: ``MidlineDefectError`` or "no defect" with the reason).
Each cut scan goes through ``engine.defect.run`` from scratch (plane included); the template's voxels are compared
with the removed bone (Dice, precision, recall), and the rim gap is the template's (``DefectResult.rim``). The
cranium (real defect, slices about 55-85) gives its template's volume and place. A table in Markdown is printed
(``docs/defect.md`` holds it).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from engine.data import HEADSQ_LEVEL, HEADSQ_SPACING_ZYX_MM, HEADSQ_ZIP
from engine.params import OrientParams

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
# the scans: file, voxel size (z, y, x), bone level (stored units), stack orientation, the cranial slices (the ray
# origin is the skull's centroid there), and the places (patient directions, the side's sign on x)
SCANS: dict[str, dict[str, Any]] = {
    "headsq": {
        "path": HEADSQ_ZIP,
        "spacing": HEADSQ_SPACING_ZYX_MM,
        "level": HEADSQ_LEVEL,
        "orient": OrientParams(first_slice="superior"),
        "cranial_slices": (4, 18),  # the top slice is the scan's border: defects there would have no rim
        # the scan starts at the orbits' roofs: no vault above, so the places are around the braincase's ring
        "places": {"frontal": (0.5, -0.85, 0.0), "temporal": (1.0, -0.1, 0.0), "posterolateral": (0.75, 0.65, 0.0)},
    },
    "head_phantom": {
        "path": SHARED / "head_phantom_dicom" / "head_phantom_png16.zip",
        "spacing": (5.0, 0.451171875, 0.451171875),
        "level": 1324.0,
        "orient": OrientParams(first_slice="inferior"),
        "cranial_slices": (12, 27),
        "places": {
            "frontal": (0.5, -0.85, 0.15),
            "parietal": (0.75, 0.1, 0.45),
            "temporal": (1.0, -0.1, 0.0),
            "occipital": (0.5, 0.85, 0.1),
        },
    },
    "cranium": {
        "path": SHARED / "cranium_ct" / "cranium_ct_png16.zip",
        "spacing": (1.5, 0.9570312, 0.9570312),
        "level": 1324.0,
        "orient": OrientParams(first_slice="inferior", flip_ap=True),  # its face is toward higher rows
        "cranial_slices": (55, 107),
        "real_defect_slices": (55, 85),
    },
}
# across the midline: centred on the intact skull's plane, or moved 12 mm to the left of it (direction, diameter,
# offset from the plane)
MIDLINE = {
    "frontal, centred on the midline": ((0.0, -0.9, 0.3), 40.0, 0.0),
    "frontal, across the midline off-centre": ((0.0, -0.9, 0.3), 50.0, 12.0),
}


def _load(name: str) -> Any:
    from engine.io import load_volume

    cfg = SCANS[name]
    return load_volume(cfg["path"], spacing_zyx_mm=cfg["spacing"])


def _run(volume: Any, cfg: dict[str, Any], device: str) -> tuple[Any, str, float]:
    from engine.defect import DefectParams, run
    from engine.errors import InputError

    t0 = time.perf_counter()
    try:
        res = run(volume, DefectParams(), cfg["level"], device, orient=cfg["orient"])
        return res, "template", time.perf_counter() - t0
    except InputError as exc:
        return None, f"{type(exc).__name__}: {exc}", time.perf_counter() - t0


def _angle(a: Any, b: Any) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(np.dot(a, b)))))))


def _case(volume: Any, cfg: dict[str, Any], device: str, intact_plane: Any, removed: Any, **row: Any) -> dict[str, Any]:
    from engine.defect.synthetic import dice

    res, outcome, secs = _run(volume, cfg, device)
    row.update(outcome=outcome if res is None else "template", seconds=round(secs, 3))
    if res is None:
        return row
    mask = res.full_mask()
    rim = res.rim()
    row.update(
        template_mm3=round(res.volume_mm3, 1),
        template_voxel_mm3=round(float(mask.sum()) * res.voxel_mm3, 1),
        rim_gap_voxels=round(rim["gap_voxels"], 3),
        rim_gap_mm=round(rim["gap_mm"], 3),
        rim_contact=round(rim["contact_share"], 3),
        side=res.side,
        watertight=bool(res.mesh_stats["watertight"]),
        plane_residual_mm=round(res.plane.residual_mm, 3),
        slices=[int(v) for v in np.argwhere(mask)[:, 0][[0, -1]]] if mask.any() else None,
        centroid_lps_mm=[round(float(v), 1) for v in res.to_json()["defect"]["centroid_lps_mm"]],
        stage_seconds={k: round(v, 3) for k, v in res.seconds.items()},
    )
    if intact_plane is not None:
        row["plane_vs_intact_deg"] = round(_angle(res.plane.normal, intact_plane.normal), 3)
        row["plane_vs_intact_mm"] = round(abs(res.plane.offset_mm - intact_plane.offset_mm), 3)
    if removed is not None:
        inter = int((mask & removed).sum())
        row.update(
            dice=round(dice(mask, removed), 4),
            precision=round(inter / max(int(mask.sum()), 1), 4),
            recall=round(inter / max(int(removed.sum()), 1), 4),
        )
    return row


def evaluate(name: str, device: str, sizes: list[float], log: Any = print) -> list[dict[str, Any]]:
    """Every case of one scan (see the module)."""
    from engine.defect import find_symmetry_plane
    from engine.defect.synthetic import cut_defect

    cfg = SCANS[name]
    volume = _load(name)
    rows: list[dict[str, Any]] = []
    real = "real_defect_slices" in cfg
    intact = _case(volume, cfg, device, None, None, scan=name, case="as scanned (real defect)" if real else "intact",
                   expected="NoDefectError")  # fmt: skip
    rows.append(intact)
    log(_line(intact))
    try:
        intact_plane = find_symmetry_plane(volume, cfg["level"], orient=cfg["orient"])
    except Exception:
        intact_plane = None
    if real:
        intact["expected"] = f"template at slices {cfg['real_defect_slices'][0]}-{cfg['real_defect_slices'][1]}"
        return rows
    for place, direction in cfg["places"].items():
        for sign, side in ((1.0, "left"), (-1.0, "right")):
            u = (sign * direction[0], direction[1], direction[2])
            for size in sizes:
                cut = cut_defect(volume, cfg["level"], u, size, slices=cfg["cranial_slices"], orient=cfg["orient"])
                row = _case(cut.volume, cfg, device, intact_plane, cut.removed, scan=name, case=f"{place} {side}",
                            diameter_mm=size, removed_mm3=round(cut.removed_mm3, 1), expected=f"template, {side}",
                            entry_lps_mm=[round(v, 1) for v in cut.entry_lps_mm])  # fmt: skip
                rows.append(row)
                log(_line(row))
    for label, (u, size, off) in MIDLINE.items():
        cut = cut_defect(volume, cfg["level"], u, size, slices=cfg["cranial_slices"], orient=cfg["orient"],
                         plane=intact_plane, offset_mm=off)  # fmt: skip
        expected = "MidlineDefectError" if off else "MidlineDefectError or NoDefectError (both sides missing)"
        row = _case(cut.volume, cfg, device, intact_plane, cut.removed, scan=name, case=label, diameter_mm=size,
                    removed_mm3=round(cut.removed_mm3, 1), expected=expected,
                    entry_lps_mm=[round(v, 1) for v in cut.entry_lps_mm])  # fmt: skip
        rows.append(row)
        log(_line(row))
    return rows


def _line(row: dict[str, Any]) -> str:
    keys = ("scan", "case", "diameter_mm", "removed_mm3", "outcome", "dice", "precision", "recall", "rim_gap_voxels",
            "template_mm3", "side", "slices", "seconds")  # fmt: skip
    return "  ".join(f"{k}={row[k]}" for k in keys if k in row)[:400]


def markdown(rows: list[dict[str, Any]]) -> str:
    """The table of ``docs/defect.md``."""
    out = [
        "| scan | case | diameter (mm) | removed (mm³) | outcome | Dice | precision | recall | rim gap (voxels) | "
        "rim gap (mm) | template (mm³) | plane Δ (°) | seconds |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def f(row: dict[str, Any], key: str, fmt: str = "{}") -> str:
        v = row.get(key)
        return "" if v is None else fmt.format(v)

    for r in rows:
        outcome = r["outcome"] if r["outcome"] == "template" else r["outcome"].split(":")[0]
        out.append(
            f"| {r['scan']} | {r['case']} | {f(r, 'diameter_mm', '{:g}')} | {f(r, 'removed_mm3', '{:,.0f}')} | "
            f"{outcome} | {f(r, 'dice', '{:.3f}')} | {f(r, 'precision', '{:.3f}')} | {f(r, 'recall', '{:.3f}')} | "
            f"{f(r, 'rim_gap_voxels', '{:.2f}')} | {f(r, 'rim_gap_mm', '{:.2f}')} | "
            f"{f(r, 'template_mm3', '{:,.0f}')} | "
            f"{f(r, 'plane_vs_intact_deg', '{:.2f}')} | {f(r, 'seconds', '{:.2f}')} |"
        )
    return "\n".join(out)


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per scan: the synthetic one-sided cases' Dice and rim gap (mean, min/max), and how many met the targets."""
    out: dict[str, Any] = {}
    for scan in sorted({r["scan"] for r in rows}):
        one = [r for r in rows if r["scan"] == scan and r["expected"].startswith("template,")]
        found = [r for r in one if "dice" in r]
        if not one:
            continue
        d = np.array([r["dice"] for r in found]) if found else np.zeros(0)
        g = np.array([r["rim_gap_voxels"] for r in found]) if found else np.zeros(0)
        out[scan] = {
            "cases": len(one),
            "templates": len(found),
            "dice_mean": round(float(d.mean()), 4) if len(d) else None,
            "dice_min": round(float(d.min()), 4) if len(d) else None,
            "dice_at_least_0.7": int((d >= 0.7).sum()),
            "rim_gap_voxels_mean": round(float(g.mean()), 4) if len(g) else None,
            "rim_gap_voxels_max": round(float(g.max()), 4) if len(g) else None,
            "rim_gap_at_most_1_voxel": int((g <= 1.0).sum()),
            "right_side": sum(1 for r in found if r["expected"].endswith(r.get("side", "?"))),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scans", default="headsq,head_phantom,cranium")
    ap.add_argument("--sizes", default="20,30,40")
    ap.add_argument("--out", default="benchmarks/results/defect_quality_cpu.json")
    args = ap.parse_args(argv)
    from engine.device import init_runtime, resolve_device

    init_runtime()
    dev = resolve_device(args.device)
    sizes = [float(s) for s in args.sizes.split(",")]
    rows: list[dict[str, Any]] = []
    for name in args.scans.split(","):
        if not Path(SCANS[name]["path"]).exists():
            print(f"{name}: {SCANS[name]['path']} is absent, skipped")
            continue
        rows += evaluate(name, args.device, sizes)
    result = {
        "benchmark": "defect_quality",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "device": str(dev),
        "device_name": getattr(dev, "name", str(dev)),
        "machine": platform.processor() or platform.machine(),
        "sizes_mm": sizes,
        "summary": summary(rows),
        "rows": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(markdown(rows))
    print(json.dumps(result["summary"], indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
