"""Progress of a run as one fraction: stages weighted by their expected share of the time, and progress inside a
stage (slices loaded, decimation passes) reported as a fraction of that stage.

The weights are the stages' shares of the pipeline's time on the real scans (``benchmarks/results/pipeline_*``):
quadric decimation is about nine tenths of it on the CPU and on the GPU, so a bar that advanced by stage count sat
at 62 % through most of the run.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

# relative expected time per pipeline stage (sums to 100)
STAGE_WEIGHTS: dict[str, float] = {
    "preprocess": 4.0,
    "upload": 1.0,
    "gaussian": 2.0,
    "isosurface": 3.0,
    "islands": 1.0,
    "decimate": 85.0,
    "smooth": 3.0,
    "normals": 1.0,
}

Progress = Callable[[str, float], None]
Fraction = Callable[[float], None]


class StageProgress:
    """Turns "stage started / this far inside it / done" into ``on_progress(stage, fraction_of_run)`` calls.

    Args:
        stages: the stages in the order they run.
        on_progress: called as ``on_progress(stage, fraction)``, the fraction of the whole run in [0, 1], never
            decreasing; None: nothing is reported.
        weights: expected relative time per stage; a stage without a weight counts 1.
    """

    def __init__(
        self, stages: Sequence[str], on_progress: Progress | None, weights: dict[str, float] | None = None
    ) -> None:
        w = STAGE_WEIGHTS if weights is None else weights
        self._weight = {s: max(0.0, float(w.get(s, 1.0))) for s in stages}
        total = sum(self._weight.values()) or 1.0
        self._start: dict[str, float] = {}  # weight done before each stage
        acc = 0.0
        for s in stages:
            self._start[s] = acc
            acc += self._weight[s]
        self._total = total
        self._cb = on_progress
        self._last = 0.0

    def _emit(self, stage: str, fraction: float) -> None:
        self._last = max(self._last, min(1.0, fraction))
        if self._cb is not None:
            self._cb(stage, self._last)

    def start(self, stage: str) -> None:
        """The stage begins."""
        self._emit(stage, self._start[stage] / self._total)

    def within(self, stage: str, fraction: float) -> None:
        """The stage is ``fraction`` (0..1) done: the callback a long stage calls (slices, passes)."""
        f = min(1.0, max(0.0, float(fraction)))
        self._emit(stage, (self._start[stage] + f * self._weight[stage]) / self._total)  # exactly 1.0 at the end

    def end(self, stage: str) -> None:
        """The stage is done."""
        self.within(stage, 1.0)

    def inside(self, stage: str) -> Fraction:
        """``within`` bound to one stage: the ``on_progress(fraction)`` callback to hand to that stage's code."""
        return lambda fraction: self.within(stage, fraction)


def span(on_progress: Progress | None, stage: str, lo: float, hi: float) -> Fraction:
    """A ``fraction`` callback that reports ``stage`` at ``lo + fraction * (hi - lo)`` (e.g. loading as the first
    tenth of a command's bar)."""

    def report(fraction: float) -> None:
        if on_progress is not None:
            on_progress(stage, lo + min(1.0, max(0.0, fraction)) * (hi - lo))

    return report
