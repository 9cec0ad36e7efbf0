"""The memory budgets, device and host: one object from the edge (the CLI, the worker) to every stage.

``Budget.of(max_device_bytes)`` parses the budget once (``"2GiB"``, a byte count, ``None`` for none, or a
``Budget`` as it is) and carries what the stages plan with:

* ``costs``: the device bytes per face of each stage's working set (``Costs``, the one table of them, measured on
  the H100 and the CPU: docs/benchmarks.md, "Any scan size in a fixed memory budget");
* the shares of the budget that a slab of the streamed volume stages and the decimated groups held on the device
  may take;
* the strategies the budget chooses by itself unless told: the slab groups' finish (one last pass or the seams),
  a device seam pass beside the joined groups, how many borders a seam batch takes, how small a device tile may be,
  where a stage past the budget goes (the host), the plane feed's ring. Tests and diagnosis set these fields to
  take a path on purpose, instead of patching the modules.

``engine.job.pipeline.reconstruct`` chooses its plan once from the budget (the whole volume at once, or streamed in
slabs), and every stage gets the ``Budget`` (``beside(held)`` where part of it is already taken) rather than bytes
to branch on. The peak actually used is measured by ``engine.backend.memory.PeakMemory``. Importing this module
never loads Warp.

``host_bytes`` (``Budget.of(device).with_host(host)``; CLI ``--max-host-bytes``, ``BONEMESH_MAX_HOST_BYTES``) bounds
the host memory of a job: a scan whose voxels take more than ``host_volume_share`` of it is not loaded whole but
read slab by slab from disk or its store (``engine.io.slabs``) through the streamed plan, its reads at most
``host_read_share`` of it at a time; on a device whose memory is the host's (Warp's CPU, OpenCL on the CPU) the
device budget comes out of it (``for_device``: ``host_device_share`` of it unless a smaller one is given).
docs/host-memory.md.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    import warp as wp

    from engine.report import Placement

__all__ = ["STATS_CHUNK_FACES", "Budget", "BudgetSpec", "Costs", "mib", "parse_bytes"]

STATS_CHUNK_FACES = 1 << 22  # the model's checks measure its faces this many at a time (20 B each)
LAYOUT_CHUNK_FACES = 1 << 20  # write_outputs: the STL facets (48 B a face) go to the host this many at a time
GROUP_MODES = ("last pass", "seams")

_UNITS = {"": 1, "b": 1, "k": 1 << 10, "kb": 1000, "kib": 1 << 10, "m": 1 << 20, "mb": 10**6, "mib": 1 << 20}
_UNITS |= {"g": 1 << 30, "gb": 10**9, "gib": 1 << 30, "t": 1 << 40, "tb": 10**12, "tib": 1 << 40}


def parse_bytes(text: str | int | None) -> int | None:
    """``"8GiB"``, ``"512 MiB"``, ``"2G"`` (binary) or a plain byte count; ``None``, ``""`` or ``"0"``: no budget.

    Raises:
        ValueError: a negative count, or text that is not a byte count with an optional unit.
    """
    if text is None or isinstance(text, int):
        if isinstance(text, int) and text < 0:
            raise ValueError(f"a memory budget must be positive, got {text}")
        return text or None
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-zA-Z]*)\s*", str(text))
    if not m or m.group(2).lower() not in _UNITS:
        raise ValueError(f"a memory budget is a byte count with an optional unit (e.g. 8GiB, 512MiB), got {text!r}")
    value = int(float(m.group(1)) * _UNITS[m.group(2).lower()])
    return value or None


def mib(n: int) -> str:
    """A byte count for messages: ``"1,024 MiB"``."""
    return f"{n / 2**20:,.0f} MiB"


@dataclass(frozen=True)
class Costs:
    """Device bytes the stages plan with, per face of a triangle mesh with about half as many vertices as faces.

    Args:
        mesh: a mesh: positions (12 B per vertex) and faces (12 B).
        decimate: a decimation in one piece: the mesh, its copy, stars, classes, quadrics, per-edge keys and
            positions.
        piece: a piece of a mesh (a seam or a tile) decimated beside it: split off (12 B), then decimated.
        finish: islands, smoothing, normals and the model's checks: the mesh, its stars (18 B), smoothing's moved
            copy and flags or the compacted copy of islands (measured on the H100 and the CPU: at most 46 B).
        islands: speck removal on a mesh already on the device: its pieces' labels and measures, a copy of its
            faces and their compaction (measured on the H100: 33 B beyond the mesh).
        layout: write_outputs' layout: the mesh and its normals (24 B), the faces rewound (12 B), the patient,
            viewing and glTF copies of positions and normals (30 B); plus 48 B a face of STL facets per chunk.
        held: the model and its patient and viewing copies, held while its viewing copies are made.
        cluster: clustering a viewing copy: the mesh, its clustering's quadrics and cells, and two copies made from
            them (measured on the H100: 106 B per face of its input, the 17.6 M-face phantom stacked three times).
        stats_chunk_faces: the model's checks measure its faces this many at a time (20 B each).
        layout_chunk_faces: the STL facets go to the host this many faces at a time.
    """

    mesh: int = 18
    decimate: int = 300
    piece: int = 12 + 300
    finish: int = 52
    islands: int = 40
    layout: int = 72
    held: int = 60
    cluster: int = 120
    stats_chunk_faces: int = STATS_CHUNK_FACES
    layout_chunk_faces: int = LAYOUT_CHUNK_FACES

    def finish_bytes(self, n_faces: int) -> int:
        """Device bytes the finishing stages of an ``n_faces`` model need (``finish`` and the checks' chunk of face
        measures)."""
        return n_faces * self.finish + min(n_faces, self.stats_chunk_faces) * 20

    def layout_bytes(self, n_faces: int) -> int:
        """Device bytes of laying out an ``n_faces`` model for its files (``engine.job.outputs.lay_out``)."""
        return n_faces * self.layout + min(n_faces, self.layout_chunk_faces) * 48


@dataclass(frozen=True)
class Budget:
    """A device memory budget and the plan the stages make within it.

    Args:
        bytes: the budget in bytes; None: no budget (the whole volume goes up at once, nothing is planned).
        costs: the per-face costs the stages plan with (``Costs``).
        slab_share: the share of the budget for one slab of the volume stages when the whole mesh is kept
            (undecimated);
        stream_slab_share: or when the mesh is decimated in groups of slabs (besides a slab, only the groups
            decimated so far, up to ``spill_share``, and the slabs' meshes not yet decimated stay);
        spill_share: decimated groups held on the device beyond this share go to the host.
        group_room_share: the share of the room beside the streamed volume's working set that the slab groups and
            their decimation may use (less: smaller groups, more borders between them).
        group_mode: the slab groups' finish, "last pass" (the groups keep some slack for one pass across them all)
            or "seams" (the groups go to the ratio; only the faces near their borders get another pass); None:
            chosen from the first group's size.
        last_pass: whether the joined groups get one last pass on the device; None: where their decimation fits.
        seams_beside: whether groups spilled to the host leave room for a seam pass on the device beside them;
            None: computed from ``costs``.
        seam_batch_borders: at most this many group borders in one device seam pass; None: as many as fit.
        max_tiles: device tiled rounds need tiles of at least 1 / ``max_tiles`` of the mesh to fit beside it (else
            the rounds run from the host).
        host_fallback: whether work past the budget goes to Warp's CPU device (outside the budget); None: from a GPU
            only (on the CPU device, whose memory the budget is, such work stays an error); True: from any device.
        feed_ring_bytes: the plane feed's ring of exactly this many bytes, on any device (as on a CUDA device);
            None: sized from the slabs, and used on CUDA devices only.
        host_bytes: the host memory bound of a job (None: none): see the module docstring.
        host_volume_share: a scan whose voxels take at most this share of ``host_bytes`` is loaded whole.
        host_device_share: on a host device, the device budget's share of ``host_bytes`` (at most).
        host_read_share: the scan's planes read from disk (the plane feed's ring, a direct read) take at most this
            share of ``host_bytes`` at a time.
    """

    bytes: int | None = None
    costs: Costs = field(default_factory=Costs)
    slab_share: float = 0.25
    stream_slab_share: float = 0.5
    spill_share: float = 0.25
    group_room_share: float = 1.0
    group_mode: str | None = None
    last_pass: bool | None = None
    seams_beside: bool | None = None
    seam_batch_borders: int | None = None
    max_tiles: int = 64
    host_fallback: bool | None = None
    feed_ring_bytes: int | None = None
    host_bytes: int | None = None
    host_volume_share: float = 0.5
    host_device_share: float = 0.5
    host_read_share: float = 0.125

    def __post_init__(self) -> None:
        for name in ("bytes", "host_bytes"):
            n = getattr(self, name)
            if n is not None and (not isinstance(n, int) or isinstance(n, bool)):
                raise ValueError(f"Expected a budget of whole bytes or None, got {name}={n!r}")
        for name in ("slab_share", "stream_slab_share", "spill_share"):
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"Expected {name} in (0, 1), got {getattr(self, name)}")
        if not 0 < self.group_room_share <= 1:
            raise ValueError(f"Expected group_room_share in (0, 1], got {self.group_room_share}")
        if self.group_mode is not None and self.group_mode not in GROUP_MODES:
            raise ValueError(f"Expected group_mode in {GROUP_MODES} or None, got {self.group_mode!r}")

    @classmethod
    def of(cls, spec: BudgetSpec = None) -> Budget:
        """The budget of ``spec``: a ``Budget`` as it is, else ``Budget(parse_bytes(spec))``.

        Raises:
            ValueError: as ``parse_bytes``.
        """
        if isinstance(spec, Budget):
            return spec
        return cls(parse_bytes(spec))

    def with_host(self, spec: str | int | None) -> Budget:
        """The same budget with a host memory bound (``parse_bytes``: ``"64GiB"``, a byte count, None for none).

        Raises:
            ValueError: as ``parse_bytes``.
        """
        return dataclasses.replace(self, host_bytes=parse_bytes(spec))

    def for_device(self, device: Any) -> Budget:
        """The budget on ``device`` (a backend, or a Warp device): where its memory is the host's and a host bound
        is set, the device budget comes out of it (at most ``host_device_share`` of it); else as it is."""
        if self.host_bytes is None or not _is_host(device):
            return self
        share = int(self.host_bytes * self.host_device_share)
        return self if self.bytes is not None and self.bytes <= share else self.with_bytes(share)

    @property
    def whole_volume_bytes(self) -> int | None:
        """The most bytes of voxels loaded whole under the host bound (None: no bound)."""
        return None if self.host_bytes is None else int(self.host_bytes * self.host_volume_share)

    @property
    def host_read_bytes(self) -> int | None:
        """The most bytes of planes read from disk at a time under the host bound (None: no bound)."""
        return None if self.host_bytes is None else int(self.host_bytes * self.host_read_share)

    @property
    def limited(self) -> bool:
        """Whether there is a budget to keep to (the streamed plan), or none (the whole volume at once)."""
        return self.bytes is not None

    def fits(self, need: int) -> bool:
        """Whether ``need`` bytes fit (always, without a budget)."""
        return self.bytes is None or need <= self.bytes

    def fits_decimation(self, n_faces: int) -> bool:
        """Whether a decimation of ``n_faces`` in one piece fits."""
        return self.fits(n_faces * self.costs.decimate)

    def last_pass_fits(self, n_faces: int) -> bool:
        """Whether joined slab groups of ``n_faces`` get one last pass on the device (``last_pass``, else where it
        fits)."""
        return self.fits_decimation(n_faces) if self.last_pass is None else self.last_pass

    def share(self, fraction: float) -> int:
        """``fraction`` of the budget in bytes (of a limited budget)."""
        assert self.bytes is not None
        return int(self.bytes * fraction)

    def beside(self, held: int) -> Budget:
        """What is left beside ``held`` bytes already in use (no budget stays none)."""
        return self if self.bytes is None else dataclasses.replace(self, bytes=self.bytes - held)

    def with_bytes(self, n: int | None) -> Budget:
        """The same plan with another byte count."""
        return dataclasses.replace(self, bytes=n)

    def host_for(self, device: Any) -> wp.Device | None:
        """Where work goes that cannot fit this budget on ``device`` (a Warp device or an ``engine.backend``
        backend; the finished model's islands, smoothing, normals and file layout): Warp's CPU device, outside the
        budget (``host_fallback``); ``None`` where it stays an error (by default a CPU device itself, whose memory
        the budget is)."""
        import warp as wp

        if self.host_fallback or (self.host_fallback is None and not _is_host(device)):
            return wp.get_device("cpu")
        return None

    def place(self, device: Any, need: int, what: str, remedy: str = "") -> tuple[Any, Placement | None]:
        """Where work that needs ``need`` bytes of device memory runs: ``(device, None)`` within the budget; past it
        ``(host, note)``, the host of ``host_for`` with a note for the report (``device``, ``reason``).

        Raises:
            BudgetError: past the budget where there is no host to go to, naming the budget that works (``what``:
                the work, ``remedy``: another way out).
        """
        from engine.errors import BudgetError

        if self.bytes is None or need <= self.bytes:
            return device, None
        reason = f"{what} needs about {mib(need)} of device memory, over the budget of {mib(self.bytes)}"
        host = self.host_for(device)
        if host is None:
            raise BudgetError(f"{reason}: give at least {mib(need)}{remedy}", needed=need)
        return host, {"device": str(host), "reason": reason}


def _is_host(device: Any) -> bool:
    """Whether ``device`` (a backend of ``engine.backend``, or a Warp device) computes in the host's memory."""
    if hasattr(device, "is_host") and not callable(device.is_host):
        return bool(device.is_host)
    return not bool(getattr(device, "is_cuda", False))


BudgetSpec = Budget | int | str | None
