"""Is the series whole? Checks run on every input before anything is reconstructed.

A model built from part of a series looks like a model: a DICOMweb answer cut short once gave 3 of 122 images, and
the loader resampled them at 53 mm into a "succeeded" job. So a series is refused, with the images named, when:

* it has fewer than ``MIN_SLICES`` images (a volume needs depth: the 3x3x3 Gaussian and the cubes need 3 planes);
* a slice is missing: a gap along the slice normal of a whole number k >= 2 of the spacing of the evenly spaced
  run of slices beside it (k - 1 slices left out), or of more than ``MAX_BRIDGE`` spacings;
* two images lie at the same position with different pixels (identical ones, the same image sent twice, are kept
  once and counted in the report);
* for an image stack without positions, the numbers in its file names step evenly except for holes.

Genuinely uneven acquisitions stay accepted and are resampled as before: runs of slices at different spacings
(variable-increment protocols: runs of ``MIN_RUN`` equal gaps or more, each gap held to the larger spacing of the
runs beside it), transition gaps between runs that are not whole multiples (two stacks joined at an offset), and
gantry tilt. The report says which layout was found (``layout``) and how many images were used.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine.errors import IncompleteSeriesError

MIN_SLICES = 3  # fewer images than this are not a volume
MIN_RUN = 3  # this many equal gaps in a row are a run at a spacing of its own (variable-increment protocols)
RUN_TOLERANCE = 0.05  # gaps within 5 % of each other belong to one run
WHOLE_STEPS = 0.15  # a gap within this many spacings of 2, 3, ... spacings is slices left out
MAX_BRIDGE = 3.0  # a gap of more spacings than this is refused whatever its size (nothing can bridge it)
SAME_POSITION_MM = 1e-3  # two images closer than this along the normal lie at the same position
_NAMED = 6  # at most this many names in a message


@dataclass
class Completeness:
    """What the checks found (``report()`` is what ``report.json`` says under ``input.source.completeness``)."""

    images: int
    layout: str  # "regular", "variable spacing" (DICOM); "numbered stack", "unnumbered stack" (image stacks)
    spacing_mm: float | None = None
    duplicates_dropped: int = 0
    runs: list[dict[str, Any]] = field(default_factory=list)

    def report(self) -> dict[str, Any]:
        out: dict[str, Any] = {"checked": True, "complete": True, "images_used": self.images, "layout": self.layout}
        if self.spacing_mm is not None:
            out["slice_spacing_mm"] = round(self.spacing_mm, 6)
        if self.duplicates_dropped:
            out["duplicates_dropped"] = self.duplicates_dropped
        if self.runs:
            out["runs"] = self.runs
        return out


def _names(names: Sequence[str]) -> str:
    shown = ", ".join(names[:_NAMED])
    return shown + (f" and {len(names) - _NAMED} more" if len(names) > _NAMED else "")


def check_count(n: int, label: str) -> None:
    """Refuse a series of fewer than ``MIN_SLICES`` images.

    Raises:
        IncompleteSeriesError: too few images.
    """
    if n < MIN_SLICES:
        raise IncompleteSeriesError(
            f"{label}: the series has {n} image(s); a volume needs at least {MIN_SLICES} slices. If images are "
            "missing, send the whole series again"
        )


def _runs(gaps: np.ndarray) -> list[tuple[int, int, float]]:
    """Maximal runs of nearly equal consecutive gaps: (first gap index, count, mean gap)."""
    runs: list[tuple[int, int, float]] = []
    start, total = 0, 0.0  # the run so far: its first gap and the sum of its gaps (a running mean, not a re-sum)
    for i in range(len(gaps) + 1):
        if i < len(gaps):
            ref = total / (i - start) if i > start else float(gaps[i])
            if abs(float(gaps[i]) - ref) <= RUN_TOLERANCE * ref:
                total += float(gaps[i])
                continue
        if i > start:
            runs.append((start, i - start, total / (i - start)))
        start, total = i, float(gaps[i]) if i < len(gaps) else 0.0
    return runs


def _leaves_out_slices(ratio: float) -> bool:
    """Whether a gap of ``ratio`` expected spacings leaves slices out."""
    return ratio > MAX_BRIDGE or (ratio >= 2 - WHOLE_STEPS and abs(ratio - round(ratio)) <= WHOLE_STEPS)


def check_positions(d: np.ndarray, names: Sequence[str], label: str, thickness_mm: float | None = None) -> Completeness:
    """Check slice positions along the normal (sorted, duplicates already removed) for missing slices.

    Args:
        d: positions along the slice normal in mm, ascending, one per image.
        names: the images' names in the same order (for the message).
        label: the input's name for messages.
        thickness_mm: the images' slice thickness, used as the expected spacing when no run of equal gaps exists.

    Raises:
        IncompleteSeriesError: too few images, or a gap that leaves out slices (the message names the images on
            either side and the number missing).
    """
    check_count(len(d), label)
    gaps = np.diff(np.asarray(d, dtype=np.float64))
    runs = _runs(gaps)
    long_runs = [r for r in runs if r[1] >= MIN_RUN]
    if not long_runs:  # no spacing to trust anywhere: the slice thickness says what a contiguous series would be
        expected = np.full(len(gaps), thickness_mm if thickness_mm else float(np.median(gaps)))
        if not thickness_mm and len(gaps) < MIN_RUN:
            expected[:] = float(np.min(gaps))
    else:
        # each gap is held to the larger spacing of the nearest long runs before and after it
        expected = np.zeros(len(gaps))
        for i in range(len(gaps)):
            before = [r[2] for r in long_runs if r[0] <= i]
            after = [r[2] for r in long_runs if r[0] + r[1] - 1 >= i]
            near = [x for x in (before[-1] if before else None, after[0] if after else None) if x is not None]
            expected[i] = max(near)
    ratio = gaps / expected
    holes = [i for i in range(len(gaps)) if _leaves_out_slices(float(ratio[i]))]
    if holes:
        parts = []
        for i in holes[:_NAMED]:
            missing = max(round(ratio[i]) - 1, 1)
            parts.append(
                f"{missing} slice(s) missing between {names[i]} and {names[i + 1]} (a gap of {gaps[i]:.4g} mm where "
                f"the series steps {expected[i]:.4g} mm)"
            )
        more = f"; {len(holes) - _NAMED} more gaps" if len(holes) > _NAMED else ""
        raise IncompleteSeriesError(
            f"{label}: the series is incomplete ({len(d)} images): " + "; ".join(parts) + more + ". Nothing was "
            "reconstructed: send the whole series (a model built across the gap would be wrong)"
        )
    layout = "regular" if len(runs) == 1 else "variable spacing"
    described = [{"images": r[1] + 1, "spacing_mm": round(r[2], 4)} for r in long_runs] if len(runs) > 1 else []
    return Completeness(images=len(d), layout=layout, spacing_mm=float(np.median(gaps)), runs=described)


def same_position_groups(d: np.ndarray) -> list[list[int]]:
    """Indices (into ascending ``d``) of images at the same position, in groups of two or more."""
    groups: list[list[int]] = []
    for k in range(1, len(d)):
        if d[k] - d[k - 1] < SAME_POSITION_MM:
            if groups and groups[-1][-1] == k - 1:
                groups[-1].append(k)
            else:
                groups.append([k - 1, k])
    return groups


def drop_identical(data: np.ndarray, groups: list[list[int]], names: Sequence[str], label: str) -> list[int]:
    """The indices to keep of images whose same-position partners are identical (pixels after rescale).

    Raises:
        IncompleteSeriesError: two images at one position differ (two acquisitions mixed, or a corrupt copy).
    """
    drop: set[int] = set()
    for group in groups:
        first = group[0]
        for k in group[1:]:
            if not np.array_equal(data[first], data[k]):
                raise IncompleteSeriesError(
                    f"{label}: {names[first]} and {names[k]} lie at the same slice position but hold different "
                    "images: the series mixes two acquisitions or a damaged copy; send one series with one image "
                    "per position"
                )
            drop.add(k)
    return [k for k in range(len(data)) if k not in drop]


_NUMBER = re.compile(r"(\d+)(?!.*\d)")  # the last number in a name


def check_numbering(names: Sequence[str], label: str) -> Completeness:
    """For an image stack (no positions): refuse holes in evenly stepping file numbers.

    The stack counts as numbered when every name has the same text around its last number; it then has holes when
    the numbers step by one amount except for larger steps that are multiples of it. Stacks named otherwise are
    taken in name order as before (``layout`` says "unnumbered stack").

    Raises:
        IncompleteSeriesError: numbers missing (named in the message).
    """
    keys = []
    for name in names:
        m = _NUMBER.search(name)
        if m is None:
            return Completeness(images=len(names), layout="unnumbered stack")
        keys.append((name[: m.start()], name[m.end() :], m.group(1)))
    if len({(a, b) for a, b, _ in keys}) != 1:
        return Completeness(images=len(names), layout="unnumbered stack")
    numbers = np.array(sorted(int(k[2]) for k in keys), dtype=np.int64)
    steps = np.diff(numbers)
    if np.any(steps == 0):
        return Completeness(images=len(names), layout="unnumbered stack")
    values, counts = np.unique(steps, return_counts=True)
    step = int(values[np.argmax(counts)])
    odd = steps != step
    if odd.any() and np.all(steps[odd] % step == 0) and 2 * counts.max() >= len(steps):
        prefix, suffix, _ = keys[0]
        widths = {len(k[2]) for k in keys}
        width = widths.pop() if len(widths) == 1 else 1  # zero-padded names keep their width
        missing = [
            f"{prefix}{v:0{width}d}{suffix}"
            for i in np.flatnonzero(odd)
            for v in range(int(numbers[i]) + step, int(numbers[i + 1]), step)
        ]
        raise IncompleteSeriesError(
            f"{label}: the slices are numbered in steps of {step}, but {len(missing)} are missing: "
            f"{_names(missing)}. Nothing was reconstructed: send every slice (a model built across the gap would "
            "be wrong)"
        )
    return Completeness(images=len(names), layout="numbered stack")
