"""The job parameters a client sends (flat JSON), validated field by field, and their engine form."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from engine.params import FLOAT32_MAX, INT32_MAX, SPACING_MM_MAX, SPACING_MM_MIN, check_spacing_zyx_mm


class JobParams(BaseModel):
    """Reconstruction parameters of a job (all optional; defaults are the paper's best combination).

    The iso level: ``iso`` in the scan's units, or a HU ``preset`` (DICOM is in HU; image stacks that store
    HU + an offset need ``hu_offset``, e.g. 1024), or none: 300 HU for DICOM, Otsu's level for image stacks.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    iso: float | None = Field(
        default=None, ge=-FLOAT32_MAX, le=FLOAT32_MAX, description="iso level in the scan's units"
    )
    preset: Literal["bone", "compact-bone", "spongy-bone"] | None = Field(default=None, description="HU preset")
    hu_offset: float | None = Field(
        default=None, ge=-FLOAT32_MAX, le=FLOAT32_MAX, description="the stack stores HU + this offset (for preset)"
    )
    spacing: list[float] | None = Field(
        default=None,
        min_length=3,
        max_length=3,
        description=f"voxel size [z, y, x] in mm, each in [{SPACING_MM_MIN:g}, {SPACING_MM_MAX:g}]; image stacks "
        "need it unless their TIFF tags carry it",
    )
    reduction: float | None = Field(default=None, gt=0, le=1, description="fraction of faces kept (default 0.2)")
    max_triangles: int | None = Field(
        default=None, ge=4, le=INT32_MAX, description="decimate to at most this many instead"
    )
    iterations: int = Field(default=1, ge=1, le=200, description="surface-preserving Laplacian iterations")
    angle: float = Field(default=0.5, gt=0, lt=90, description="smoothing threshold angle, degrees")
    min_island_mm3: float | None = Field(
        default=None, ge=0, le=FLOAT32_MAX, description="drop pieces smaller than this volume (mm³)"
    )
    keep_largest: int | None = Field(default=None, ge=1, le=INT32_MAX, description="keep only the N largest pieces")
    phone_max_triangles: int = Field(default=100_000, ge=100, le=2_000_000, description="phone.glb budget")
    ar_max_triangles: int = Field(default=50_000, ge=100, le=2_000_000, description="ar.glb budget")

    @field_validator("spacing")
    @classmethod
    def _plausible(cls, value: list[float] | None) -> list[float] | None:
        if value is not None:
            check_spacing_zyx_mm(value)  # the engine's own range: the CLI refuses the same
        return value

    @model_validator(mode="after")
    def _consistent(self) -> JobParams:
        if self.iso is not None and self.preset is not None:
            raise ValueError("give iso or preset, not both")
        if self.reduction is not None and self.max_triangles is not None:
            raise ValueError("give reduction or max_triangles, not both")
        return self

    def engine_params(self) -> dict[str, Any]:
        """The engine's ``ReconParams.to_dict()`` form of these parameters."""
        from engine.params import (
            DecimateParams,
            ExportParams,
            IslandParams,
            IsoParams,
            ReconParams,
            SmoothParams,
        )

        islands = None
        if self.min_island_mm3 is not None or self.keep_largest is not None:
            islands = IslandParams(min_volume_mm3=self.min_island_mm3, keep_largest=self.keep_largest)
        return ReconParams(
            iso=IsoParams(iso=self.iso, preset=self.preset, hu_offset=self.hu_offset),
            islands=islands,
            decimate=DecimateParams(
                reduction=None if self.max_triangles else (self.reduction or 0.2), max_triangles=self.max_triangles
            ),
            smooth=SmoothParams(iterations=self.iterations, angle_deg=self.angle),
            export=ExportParams(phone_max_triangles=self.phone_max_triangles, ar_max_triangles=self.ar_max_triangles),
        ).to_dict()
