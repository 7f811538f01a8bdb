"""STL, binary and ASCII: a triangle soup welded into one part.

Binary: 80-byte header, uint32 facet count, then 50 bytes per facet (normal, 3 corners as
little-endian float32, uint16 attribute).  A file is binary when its size is exactly
``84 + 50 * count`` -- even when the header starts with ``solid``, as many exporters write it.
ASCII: ``solid``/``facet normal``/``outer loop``/3 x ``vertex x y z``/``endloop``/``endfacet``
(keywords in any case, several solids allowed); other lines are kept and ignored.

Write: binary -- the 12 coordinate bytes of every facet corner of a moved vertex are patched
with float32 values; the facet normals (and attribute bytes) are left unchanged, so a normal
may no longer match its moved facet exactly (readers recompute normals, and for the small
watermark displacements the stored one stays a good approximation).  ASCII -- only the moved
corners' ``vertex`` lines change, and on them only the coordinate tokens (normals unchanged).
"""

from __future__ import annotations

import numpy as np

from core.errors import MeshFormatError
from core.formats._text import (
    BOM,
    TextMeshDocument,
    check_finite,
    decimals_of,
    gather,
    keyword_mask,
    moved_slots,
    parse_block,
    split_lines,
    strip_comments,
)
from core.formats.base import FormatSpec, Limits, MeshDocument, MeshPart, weld

_FACET = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)), ("attr", "<u2")])
_SNIFF_BYTES = 4096


def _binary_count(data: bytes) -> int | None:
    """Facet count when ``data`` has exactly the size of a binary STL, else ``None``."""
    if len(data) < 84:
        return None
    n = int.from_bytes(data[80:84], "little")
    return n if 84 + 50 * n == len(data) else None


def _ascii_head(data: bytes) -> bool:
    """``solid`` first, then a ``facet`` or ``endsolid`` soon after, and no NUL byte."""
    head = bytes(data[:_SNIFF_BYTES]).removeprefix(BOM)
    tokens = head.split(None, 64)
    if not tokens or tokens[0].lower() != b"solid" or b"\x00" in head:
        return False
    rest = [t.lower() for t in tokens[1:]]
    return b"facet" in rest or b"endsolid" in rest


def sniff(data: bytes, name: str) -> bool:
    """True for a binary STL of consistent size or an ASCII STL."""
    return _binary_count(data) is not None or _ascii_head(data)


class StlDocument(TextMeshDocument):
    """A parsed STL file (binary or ASCII); one part."""

    format = "stl"

    def __init__(
        self, data: bytes, parts: list[MeshPart], encoding: str, slot_lines: np.ndarray | None
    ) -> None:
        super().__init__(data, parts)
        self.encoding = encoding
        self._slot_lines = slot_lines
        if encoding == "binary":
            self.storage_dtype = np.dtype(np.float32)

    def quantize(self, vertices: np.ndarray, decimals: int | None = None) -> np.ndarray:
        """Positions as a :meth:`write` then a new read would give them back."""
        if self.encoding == "binary":
            return MeshDocument.quantize(self, vertices, decimals)
        return super().quantize(vertices, decimals)

    def _patch(self, vertices: list[np.ndarray], moved: list[np.ndarray], decimals: int | None) -> bytes:
        if self.encoding != "binary":
            assert self._slot_lines is not None
            return self._patch_text(vertices, moved, decimals, self._slot_lines, np.array([1, 2, 3]))
        part = self.parts[0]
        slots = moved_slots(part.slot_to_vertex, moved[0], len(part.vertices))
        if slots.size == 0:
            return self.data
        out = bytearray(self.data)
        facets = np.frombuffer(out, dtype=_FACET, count=(len(self.data) - 84) // 50, offset=84)
        new = np.asarray(vertices[0], dtype=np.float64)[part.slot_to_vertex[slots]]
        facets["corners"][slots // 3, slots % 3] = new.astype("<f4")
        del facets
        return bytes(out)


def read(data: bytes, limits: Limits, name: str = "stl") -> StlDocument:
    """Parse an STL file.

    Parameters
    ----------
    data : bytes
        The whole file.
    limits : Limits
        The facet count is checked before anything proportional is allocated, the welded
        vertex count after welding.
    name : str
        Format key (unused).

    Raises
    ------
    MeshFormatError
        Binary size not matching its facet count, malformed ASCII facet, NaN/Inf coordinate.
    LimitExceededError
    """
    data = bytes(data)
    count = _binary_count(data)
    if count is not None:
        limits.check("faces", count)
        facets = np.frombuffer(data, dtype=_FACET, count=count, offset=84)
        with np.errstate(invalid="ignore"):  # signalling NaNs; refused just below
            positions = facets["corners"].reshape(-1, 3).astype(np.float64)
        del facets
        check_finite(positions)
        encoding, slot_lines, decimals, part_name = "binary", None, None, "mesh0"
    elif _ascii_head(data):
        positions, slot_lines, decimals, part_name = _read_ascii(data, limits)
        encoding = "ascii"
    else:
        if len(data) >= 84:
            n = int.from_bytes(data[80:84], "little")
            raise MeshFormatError(
                f"binary STL declares {n} facets ({84 + 50 * n} bytes) but the file has {len(data)} bytes"
            )
        raise MeshFormatError("file too short for a binary STL and not an ASCII STL")
    triangles = np.arange(positions.shape[0], dtype=np.int64).reshape(-1, 3)
    vertices, faces, slot_to_vertex = weld(positions, triangles)
    limits.check("vertices", len(vertices))
    part = MeshPart(part_name, vertices, faces, slot_to_vertex)
    doc = StlDocument(data, [part], encoding, slot_lines)
    doc.decimals = decimals
    return doc


def _read_ascii(data: bytes, limits: Limits) -> tuple[np.ndarray, np.ndarray, int | None, str]:
    arr = np.frombuffer(data, dtype=np.uint8)
    lines = split_lines(arr)
    facet_lines = np.flatnonzero(keyword_mask(arr, lines, b"facet", fold_case=True))
    limits.check("faces", int(facet_lines.size))
    vl = np.flatnonzero(keyword_mask(arr, lines, b"vertex", fold_case=True))
    if vl.size != 3 * facet_lines.size:
        raise MeshFormatError(f"{facet_lines.size} facets but {vl.size} vertex lines (expected 3 per facet)")
    if vl.size:
        owner = np.searchsorted(facet_lines, vl, side="right") - 1
        per_facet = np.bincount(owner[owner >= 0], minlength=facet_lines.size)
        bad = np.flatnonzero(per_facet != 3)
        if owner[0] < 0 or bad.size:
            where = int(vl[0]) if owner[0] < 0 else int(facet_lines[bad[0]])
            raise MeshFormatError("facet without exactly 3 vertices", f"line {where + 1}")
    text = strip_comments(gather(arr, lines.first[vl] + 6, lines.nexts[vl]))
    block = parse_block(text, int(vl.size), np.float64, vl, spans=True, what="vertex coordinate")
    bad = np.flatnonzero(block.counts != 3)
    if bad.size:
        raise MeshFormatError("vertex line without exactly 3 coordinates", f"line {int(vl[bad[0]]) + 1}")
    positions = block.values.reshape(-1, 3)
    check_finite(positions, vl)
    assert block.tok_starts is not None and block.tok_ends is not None
    decimals = decimals_of(block.text, block.tok_starts, block.tok_ends)
    first = data[int(lines.first[0]) : int(lines.ends[0])] if len(lines) else b""
    name = first[5:].strip().decode("utf-8", "replace") if first[:5].lower() == b"solid" else ""
    return positions, lines.starts[vl], decimals, name or "mesh0"


def _why_not(data: bytes) -> str:
    """Binary STL has no magic number, its size is its signature: what the size should be."""
    if len(data) < 84:
        return ""
    n = int.from_bytes(data[80:84], "little")
    return f" (as a binary STL it declares {n:,} facets, {84 + 50 * n:,} bytes, but has {len(data):,})"


SPEC = FormatSpec("stl", "STL", "STL", ("stl",), "model/stl", sniff, read, sniff_rank=1, why_not=_why_not)
