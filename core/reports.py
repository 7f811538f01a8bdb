"""What the engine answers: the report of an embedding, a detection and a capacity measurement.

Plain frozen dataclasses of numbers, strings and lists (``to_dict()`` is their JSON), so the
service and the command line print them as they are.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

#: called with the fraction done, from 0 to 1
Progress = Callable[[float], None]


class _Report:
    """A report's JSON: ``to_dict()``, field by field."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)  # type: ignore[call-overload]


@dataclass(frozen=True)
class EmbedReport(_Report):
    """What an embedding did.  Distances are relative to the bounding-box diagonal."""

    #: the method used (asked, or chosen when none was: :data:`core.options.AUTO_METHOD`)
    method: str
    strength: float
    payload_bits: int          # payload length (32 for the key-derived default code)
    key_derived: bool          # True when no payload was given (the paper's mode)
    codeword_bits: int         # bits after CRC + error-correcting code
    carriers: int              # carrier vertices under the key (all parts); not all of them move
    copies: float              # carriers / codeword_bits
    skipped: int               # carriers left alone because they would exceed the displacement cap
    vertices_moved: int
    rms_displacement: float    # over all vertices
    max_displacement: float
    hausdorff: float           # symmetric Hausdorff distance between input and output vertices/surface
    decimals: int | None       # text formats: decimals printed for moved coordinates
    cap_factor: float          # displacement cap used, as a multiple of the default (coarse meshes)
    parts: list[dict[str, Any]] = field(default_factory=list)
    skipped_elements: int = 0  # non-triangle elements of the file, carried through untouched
    reencoded: list[str] = field(default_factory=list)  # compressed encodings re-encoded on write
    #: the layers that read the payload alone: "connectivity" (always; crops, parts of a scene) and
    #: "geometry" when the geometric layer does too (re-triangulations)
    layers: list[str] = field(default_factory=lambda: ["connectivity"])
    geometric_carriers: int = 0  # carriers of the geometric layer (all parts)

@dataclass(frozen=True)
class DetectResult(_Report):
    """Blind detection result.  ``detected`` means the CRC verified (or, for the key-derived
    code, the bit errors are few enough that ``false_positive_probability`` < 1e-6).  ``crc_ok``
    is about a payload's CRC-32: always False for the key-derived code, which has none."""

    detected: bool
    payload: str | None              # bitstring of '0'/'1'
    bit_confidence: list[float]      # per payload bit, probability that the bit is right
    false_positive_probability: float
    copies: float
    carriers: int
    crc_ok: bool
    #: the method the file was marked with; None when no method was given and only the geometric
    #: layer read the mark (its carriers are read alike whatever the method)
    method: str | None
    key_derived: bool
    bit_errors: int | None = None    # only with an expected payload
    p_value: float | None = None     # only with an expected payload
    parts: list[dict[str, Any]] = field(default_factory=list)
    #: "midpoint", "loop" or "sqrt3" when the mark was read on the mesh one subdivision step down
    #: (the file had been subdivided after marking), else None
    resampled: str | None = None
    #: iterations of uniform Laplacian smoothing (step 0.1) undone before the mark read (the file
    #: had been smoothed after marking), else None
    unsmoothed: int | None = None
    #: which carriers read the mark: "both" layers together, the "connectivity" layer alone (a
    #: cropped piece), or the "geometry" layer alone (a re-triangulated mesh); None when not read
    layer: str | None = None
    #: carriers of the geometric layer among ``carriers``
    geometric_carriers: int = 0

@dataclass(frozen=True)
class CapacityReport(_Report):
    #: the method of these figures (asked, or when none was, the one with the longer payload)
    method: str
    strength: float
    carriers: int
    max_payload_bits: int            # largest payload (carriers >= 1.5 x its codeword) verified to embed
    copies_of_default: float         # copies of the key-derived 32-bit code
    codeword_bits_default: int       # 76: the key-derived code, convolutionally coded
    expected_rms_displacement: float
    expected_max_displacement: float
    payload_bits_by_copies: dict[str, int] = field(default_factory=dict)  # copies -> largest payload
    parts: list[dict[str, Any]] = field(default_factory=list)
    #: carriers of the geometric layer an embedding of the key-derived code would have (0: none; a
    #: payload whose codeword needs more than a quarter of them gets the connectivity layer only)
    geometric_carriers: int = 0

@dataclass(frozen=True)
class EmbeddedFile:
    """The marked file: its bytes, the report, and how to send it (from the format's spec)."""

    data: bytes
    report: EmbedReport
    format: str
    media_type: str
    extension: str
