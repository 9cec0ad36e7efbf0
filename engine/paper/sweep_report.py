"""The sweep's report: the paper's enhancement score (Table 2), Tables 1 and 2 as CSV and markdown, and the plots.

Pure functions of the rows that :func:`engine.paper.sweep.run_sweep` measures (dicts keyed as ``table1.csv``); nothing
here runs the pipeline or touches a device, so the tables of a stored ``rows.jsonl`` can be rewritten on their own.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

WEIGHTS = {"accuracy": 0.6, "size": 0.3, "time": 0.1}


def enhancement_score(row: dict[str, Any], base: dict[str, Any]) -> dict[str, float]:
    """The paper's enhancement score of a row against the baseline row, as decimals.

    ``accuracy`` is the mean relative gain of RMSE % and SSIM %, ``size`` the mean relative decrease of faces and
    vertices, ``time`` the relative decrease of the total time (reconstruct + rendering);
    ``score = 0.6 * accuracy + 0.3 * size + 0.1 * time``. (The paper's best pair: 0.2641.)
    """
    acc = ((row["rmse_pct"] / base["rmse_pct"] - 1) + (row["ssim_pct"] / base["ssim_pct"] - 1)) / 2
    size = ((1 - row["faces"] / base["faces"]) + (1 - row["vertices"] / base["vertices"])) / 2
    t_row = row["reconstruct_s"] + row["rendering_s"]
    t_base = base["reconstruct_s"] + base["rendering_s"]
    tm = 1 - t_row / t_base
    score = WEIGHTS["accuracy"] * acc + WEIGHTS["size"] * size + WEIGHTS["time"] * tm
    return {"accuracy": acc, "size": size, "time": tm, "score": score}


def json_default(obj: Any) -> Any:
    """``json.dumps(default=...)`` for the rows and meta: numpy scalars and arrays as Python values, else ``str``."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


TABLE1_COLUMNS = (
    "method", "reduction", "iterations", "rmse_pct", "ssim_pct", "reconstruct_s", "rendering_s", "faces", "vertices",
    "dice", "mean_mm", "p95_mm", "hausdorff_mm", "watertight", "manifold", "components", "euler", "min_angle_p5_deg",
    "below_10deg", "volume_change_pct", "area_change_pct", "slices_compared",
)  # fmt: skip


def _order(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    rank = {"MC33": 0, "MC33GPU": 1, "GMC33GPU": 2, "EMC33GPU": 3}
    return sorted(rows, key=lambda r: (rank[r["method"]], r["reduction"] or 0, r["iterations"] or 0))


def scores(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Table 2: the enhancement score of every EMC33GPU row against MC33GPU; the best has ``best: True``."""
    base = next((r for r in rows if r["method"] == "MC33GPU"), None)
    if base is None:
        return []
    out = [
        {"reduction": r["reduction"], "iterations": r["iterations"], **enhancement_score(r, base), "best": False}
        for r in _order(rows)
        if r["method"] == "EMC33GPU"
    ]
    if out:
        max(out, key=lambda s: s["score"])["best"] = True
    return out


def _fmt(value: Any, digits: int = 2) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.{digits}f}"
    return str(value)


def tables_markdown(rows: list[dict[str, Any]], info: dict[str, Any]) -> str:
    """Tables 1 and 2 as markdown, with the facts needed to read them."""
    inp = info["input"]
    cfg = info["config"]
    lines = [
        f"Input: {inp['shape_zyx']} (z, y, x) {inp['dtype']}, spacing {inp['spacing_zyx_mm']} mm, level "
        f"{inp['level']:g}; device {info.get('device_name', info.get('device'))}.",
        f"Times: {info['timing']}. Similarity over {rows[0]['slices_compared'] if rows else 0} slice(s); distances "
        f"from {cfg['n_points']:,} samples per surface to the undecimated Gaussian + MC33 surface.",
        "",
        "Table 1.",
        "",
        "| Method | R | It | RMSE (%) | SSIM (%) | Reconstruct (s) | Rendering (s) | Faces | Vertices | Dice "
        "| Mean (mm) | Hausdorff (mm) | Watertight |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in _order(rows):
        lines.append(
            f"| {r['method']} | {_fmt(r['reduction'], 1)} | {_fmt(r['iterations'])} | {_fmt(r['rmse_pct'])} | "
            f"{_fmt(r['ssim_pct'])} | {_fmt(r['reconstruct_s'], 3)} | {_fmt(r['rendering_s'], 3)} | "
            f"{_fmt(r['faces'])} | {_fmt(r['vertices'])} | {_fmt(r['dice'], 4)} | {r['mean_mm']:.3g} | "
            f"{r['hausdorff_mm']:.3g} | {_fmt(r['watertight'])} |"
        )
    sc = scores(rows)
    if sc:
        its = sorted({s["iterations"] for s in sc})
        lines += [
            "",
            "Table 2. Enhancement score against MC33GPU (0.6 accuracy + 0.3 size + 0.1 time; best in bold).",
            "",
            "| R | " + " | ".join(f"{i} it" for i in its) + " |",
            "|---|" + "---|" * len(its),
        ]
        for red in sorted({s["reduction"] for s in sc}):
            cells = []
            for i in its:
                s = next((x for x in sc if x["reduction"] == red and x["iterations"] == i), None)
                text = "-" if s is None else f"{s['score']:.4f}"
                cells.append(f"**{text}**" if s is not None and s["best"] else text)
            lines.append(f"| {red:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_tables(rows: list[dict[str, Any]], outdir: Path, info: dict[str, Any]) -> dict[str, Path]:
    """Write ``table1.csv``, ``table2.csv``, ``tables.md`` and the two PNG plots; returns their paths."""
    import csv

    paths = {name: outdir / name for name in ("table1.csv", "table2.csv", "tables.md")}
    with paths["table1.csv"].open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TABLE1_COLUMNS)
        for r in _order(rows):
            w.writerow(["" if r[c] is None else r[c] for c in TABLE1_COLUMNS])
    with paths["table2.csv"].open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(("reduction", "iterations", "accuracy", "size", "time", "score", "best"))
        for s in scores(rows):
            w.writerow([s[k] for k in ("reduction", "iterations", "accuracy", "size", "time", "score", "best")])
    paths["tables.md"].write_text(tables_markdown(rows, info))
    paths.update(plot(rows, outdir))
    return paths


def plot(rows: list[dict[str, Any]], outdir: Path) -> dict[str, Path]:
    """``accuracy_vs_faces.png`` (RMSE % and SSIM % against faces) and ``time_vs_iterations.png``."""
    try:
        import matplotlib
    except ImportError as exc:  # the `paper` extra: not in the base install
        raise ImportError("the sweep's plots need matplotlib: pip install 'bonemesh[paper]'") from exc

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    emc = [r for r in _order(rows) if r["method"] == "EMC33GPU"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, metric, label in zip(axes, ("rmse_pct", "ssim_pct"), ("RMSE (%)", "SSIM (%)"), strict=True):
        for it in sorted({r["iterations"] for r in emc}):
            sel = sorted((r for r in emc if r["iterations"] == it), key=lambda r: r["faces"])
            ax.plot([r["faces"] for r in sel], [r[metric] for r in sel], "o-", label=f"EMC33GPU, {it} it")
        for r in rows:
            if r["method"] != "EMC33GPU":
                ax.plot(r["faces"], r[metric], "s" if r["method"] == "MC33" else "D", ms=8, label=r["method"])
        ax.set_xlabel("faces")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=8)
    fig.suptitle("Accuracy against model size")
    fig.tight_layout()
    paths = {"accuracy_vs_faces.png": outdir / "accuracy_vs_faces.png"}
    fig.savefig(paths["accuracy_vs_faces.png"], dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for red in sorted({r["reduction"] for r in emc}):
        sel = sorted((r for r in emc if r["reduction"] == red), key=lambda r: r["iterations"])
        ax.plot(
            [r["iterations"] for r in sel],
            [r["reconstruct_s"] + r["rendering_s"] for r in sel],
            "o-",
            label=f"R={red:g}",
        )
    for r in rows:
        if r["method"] == "MC33GPU":
            ax.axhline(r["reconstruct_s"] + r["rendering_s"], color="k", ls="--", label="MC33GPU")
    ax.set_xlabel("Laplacian iterations")
    ax.set_ylabel("reconstruct + rendering (s)")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    paths["time_vs_iterations.png"] = outdir / "time_vs_iterations.png"
    fig.savefig(paths["time_vs_iterations.png"], dpi=110)
    plt.close(fig)
    return paths
