"""Which received series become jobs, and with which parameters.

A series is first checked against what is never a model (a localizer/scout by its Image Type or description, a
dose report or screen capture), then against the rules in order; the first rule that matches gives the job's
parameters. A series that no rule takes is ignored, and the log names it by its UIDs only.

Rules (``BONEMESH_PACS_ROUTES``, a JSON list), e.g.::

    [{"name": "hips", "body_part": "PELVIS|HIP", "min_slices": 40, "params": {"preset": "bone", "reduction": 0.1}},
     {"name": "bone", "modality": "CT", "min_slices": 16},
     {"name": "segments", "modality": "SEG", "min_slices": 2, "params": {"segments": ["femur_left", "femur_right"]}}]

A SEG series (``modality: SEG``; its frames counted as images) becomes a label job on the CT series it references
(``service.pacs.gateway``): a model per segment, or per segment named in ``params.segments``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from core.params import JobParams

# Image Type values and series descriptions of images that are not a volume to model
NOT_A_VOLUME_TYPES = frozenset({"LOCALIZER", "SCOUT", "SCREEN SAVE", "DOSE_INFO"})
NOT_A_VOLUME_WORDS = re.compile(
    r"\b(scout|topogram|localizer|localiser|surview|scanogram|pilot|dose\s*(report|info)|patient\s*protocol)\b",
    re.IGNORECASE,
)


@dataclass(frozen=True)
class SeriesSummary:
    """What routing sees of a received series (its first image's header and the image count)."""

    study_uid: str
    series_uid: str
    modality: str
    images: int
    description: str = ""
    body_part: str = ""
    image_type: tuple[str, ...] = ()


class Rule(BaseModel):
    """One routing rule: which series it takes and the job parameters it gives them.

    Args:
        name: a label (logged, and recorded on the job).
        modality: the Modality the series must have.
        min_slices: fewest images (a few slices are no volume).
        series_description: a regular expression searched (case-insensitive) in Series Description.
        body_part: a regular expression searched (case-insensitive) in Body Part Examined.
        params: the job parameters (``JobParams``: preset, reduction, ...); default the bone preset.
    """

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=64)
    modality: str = "CT"
    min_slices: int = Field(default=16, ge=2)
    series_description: str | None = None
    body_part: str | None = None
    params: dict[str, Any] = Field(default_factory=lambda: {"preset": "bone"})

    @field_validator("series_description", "body_part")
    @classmethod
    def _regex(cls, value: str | None) -> str | None:
        if value is not None:
            try:
                re.compile(value)
            except re.error as exc:
                raise ValueError(f"not a regular expression: {exc}") from None
        return value

    @field_validator("params")
    @classmethod
    def _params(cls, value: dict[str, Any]) -> dict[str, Any]:
        JobParams.model_validate(value).job_spec()  # refused at start, not when a series arrives
        return value

    def job_params(self) -> JobParams:
        """The rule's parameters as the API's job parameters."""
        return JobParams.model_validate(self.params)

    def refusal(self, series: SeriesSummary) -> str | None:
        """Why this rule does not take the series (no patient data in the text), or None when it does."""
        if series.modality.upper() != self.modality.upper():
            return f"modality {series.modality or 'none'}, not {self.modality}"
        if series.images < self.min_slices:
            return f"{series.images} images, fewer than {self.min_slices}"
        if self.series_description and not re.search(self.series_description, series.description, re.IGNORECASE):
            return "series description does not match"
        if self.body_part and not re.search(self.body_part, series.body_part, re.IGNORECASE):
            return "body part does not match"
        return None


REFERENCE_FOLDER = "reference"  # a SEG's CT series, in the SEG job's upload (received: the gateway; fetched: worker)
# a CT becomes a bone model; a segmentation (SEG) of a CT received or already run becomes a model per segment
DEFAULT_RULES = (Rule(name="bone"), Rule(name="segments", modality="SEG", min_slices=2))


def not_a_volume(series: SeriesSummary) -> str | None:
    """Why a series is a localizer, scout, dose report or screen capture rather than a volume, or None."""
    kinds = NOT_A_VOLUME_TYPES.intersection(v.upper() for v in series.image_type)
    if kinds:
        return f"Image Type {'/'.join(sorted(kinds))}"
    if NOT_A_VOLUME_WORDS.search(series.description):
        return "a scout, localizer or dose report by its description"
    return None


def choose_rule(series: SeriesSummary, rules: Sequence[Rule]) -> tuple[Rule | None, str]:
    """The first rule that takes the series, and why (or why none does)."""
    reason = not_a_volume(series)
    if reason:
        return None, f"not a volume: {reason}"
    refusals = []
    for rule in rules:
        refusal = rule.refusal(series)
        if refusal is None:
            return rule, f"rule {rule.name!r}"
        refusals.append(f"{rule.name}: {refusal}")
    return None, ("no rule takes it (" + "; ".join(refusals) + ")") if refusals else "no routing rule is configured"
