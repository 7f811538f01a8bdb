"""Public, file-level entry points used by the service, the CLI and the benchmarks.

These functions take the uploaded bytes and return plain dataclasses; they never touch HTTP,
paths or the network.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

Progress = Callable[[float], None]

METHODS = ("ellipsoids", "planes")
DEFAULT_METHOD = "ellipsoids"


@dataclass(frozen=True)
class EmbedReport:
    """What an embedding did.  Distances are relative to the bounding-box diagonal."""

    method: str
    strength: float
    payload_bits: int          # payload length (32 for the key-derived default code)
    key_derived: bool          # True when no payload was given (the paper's mode)
    codeword_bits: int         # bits after CRC + error-correcting code
    carriers: int              # carriers moved (all parts)
    copies: float              # carriers / codeword_bits
    skipped: int               # carriers left alone because they would exceed the displacement cap
    vertices_moved: int
    rms_displacement: float    # over all vertices
    max_displacement: float
    hausdorff: float           # symmetric Hausdorff distance between input and output vertices/surface
    decimals: int | None       # text formats: decimals printed for moved coordinates
    cap_factor: float          # displacement cap used, as a multiple of the default (coarse meshes)
    parts: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class DetectResult:
    """Blind detection result.  ``detected`` means the CRC verified (or, for the key-derived
    code, the bit errors are few enough that ``false_positive_probability`` < 1e-6)."""

    detected: bool
    payload: str | None              # bitstring of '0'/'1'
    bit_confidence: list[float]      # per payload bit, probability that the bit is right
    false_positive_probability: float
    copies: float
    carriers: int
    crc_ok: bool
    method: str | None
    key_derived: bool
    bit_errors: int | None = None    # only with an expected payload
    p_value: float | None = None     # only with an expected payload
    parts: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class CapacityReport:
    method: str
    strength: float
    carriers: int
    max_payload_bits: int            # largest payload with carriers >= 1.5 x its codeword (CRC + code)
    copies_of_default: float         # copies of the key-derived 32-bit code
    codeword_bits_default: int       # 56: the key-derived code with Hamming(7,4)
    expected_rms_displacement: float
    expected_max_displacement: float
    payload_bits_by_copies: dict[str, int] = field(default_factory=dict)  # copies -> largest payload
    parts: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class EmbeddedFile:
    data: bytes
    report: EmbedReport
    format: str
    media_type: str
    extension: str


def embed_file(
    data: bytes,
    key: str | bytes,
    *,
    filename: str | None = None,
    payload: str | None = None,
    method: str = DEFAULT_METHOD,
    strength: float | None = None,
    limits: Any = None,
    progress: Progress | None = None,
) -> EmbeddedFile:
    """Watermark a mesh file; returns the same format with only moved coordinates changed."""
    from core.pipeline import embed_file as _impl

    return _impl(data, key, filename=filename, payload=payload, method=method, strength=strength,
                 limits=limits, progress=progress)


def detect_file(
    data: bytes,
    key: str | bytes,
    *,
    filename: str | None = None,
    payload: str | None = None,
    method: str | None = None,
    limits: Any = None,
    progress: Progress | None = None,
) -> DetectResult:
    """Blind detection from the file and the key only; ``method=None`` tries both methods."""
    from core.pipeline import detect_file as _impl

    return _impl(data, key, filename=filename, payload=payload, method=method, limits=limits,
                 progress=progress)


def capacity_file(
    data: bytes,
    *,
    filename: str | None = None,
    method: str = DEFAULT_METHOD,
    strength: float | None = None,
    limits: Any = None,
) -> CapacityReport:
    """Carriers and payload room without embedding."""
    from core.pipeline import capacity_file as _impl

    return _impl(data, filename=filename, method=method, strength=strength, limits=limits)


def embed_mesh(
    vertices: Any,
    faces: Any,
    key: str | bytes,
    *,
    payload: str | None = None,
    method: str = DEFAULT_METHOD,
    strength: float | None = None,
) -> tuple[Any, EmbedReport]:
    """Array-level embedding: ``(n, 3)`` vertices and ``(m, 3)`` triangles in, new vertices out."""
    from core.pipeline import embed_mesh as _impl

    return _impl(vertices, faces, key, payload=payload, method=method, strength=strength)


def detect_mesh(
    meshes: list[tuple[Any, Any]],
    key: str | bytes,
    *,
    payload: str | None = None,
    method: str | None = None,
) -> DetectResult:
    """Array-level blind detection over one or several ``(vertices, faces)`` meshes."""
    from core.pipeline import detect_mesh as _impl

    return _impl(meshes, key, payload=payload, method=method)
