"""Object File Format (OFF, ASCII), with the ``C``/``N``/``ST`` variants (``COFF``, ``NOFF``...).

Layout: a header keyword line, ``nv nf [ne]`` (on the header line or the next), ``nv`` vertex
lines (x y z then any per-vertex extras: normal, colour, texture coordinates), ``nf`` face
lines (``n i1 ... in`` then an optional colour).  ``#`` comments and blank lines may appear
anywhere.  Binary OFF and the ``4``/``n`` (other dimension) variants are refused.

Write: only the lines of moved vertices change, and on them only the x, y, z tokens.
"""

from __future__ import annotations

import re

import numpy as np

from core.errors import MeshFormatError
from core.formats._text import (
    BOM,
    Lines,
    TextMeshDocument,
    gather,
    parse_block,
    parse_vertex_lines,
    ragged_take,
    split_lines,
    strip_comments,
    triangulate,
)
from core.formats.base import FormatSpec, Limits, MeshPart, weld

_HEADER = re.compile(rb"(ST)?(C)?(N)?(4)?(n)?OFF")
_SNIFF_BYTES = 4096


def _header_keyword(token: bytes) -> re.Match[bytes] | None:
    return _HEADER.fullmatch(token)


def sniff(data: bytes, name: str) -> bool:
    """True when the first non-comment token of ``data`` is an OFF header keyword."""
    head = bytes(data[:_SNIFF_BYTES]).removeprefix(BOM)
    if b"\x00" in head:
        return False
    for line in head.split(b"\n"):
        tokens = line.split(b"#", 1)[0].split()
        if tokens:
            return _header_keyword(tokens[0]) is not None
    return False


class OffDocument(TextMeshDocument):
    """A parsed OFF file (one part, ``"mesh0"``)."""

    format = "off"
    encoding = "ascii"

    def __init__(self, data: bytes, parts: list[MeshPart], slot_lines: np.ndarray) -> None:
        super().__init__(data, parts)
        self._slot_lines = slot_lines

    def _patch(self, vertices: list[np.ndarray], moved: list[np.ndarray], decimals: int | None) -> bytes:
        return self._patch_text(vertices, moved, decimals, self._slot_lines, np.array([0, 1, 2]))


def _ints(tokens: list[bytes], line: int) -> list[int]:
    try:
        return [int(t) for t in tokens]
    except ValueError:
        raise MeshFormatError("invalid OFF element counts", f"line {line + 1}") from None


def read(data: bytes, limits: Limits, name: str = "off") -> OffDocument:
    """Parse an ASCII OFF file.

    Parameters
    ----------
    data : bytes
        The whole file.
    limits : Limits
        Declared vertex and face counts are checked before anything proportional is allocated.
    name : str
        Format key (unused).

    Raises
    ------
    MeshFormatError
        Bad header or counts, fewer lines than declared, non-numeric value, index out of range,
        a corner count that is negative, fractional or larger than the line, NaN/Inf coordinate.
        Faces of fewer than 3 corners are skipped and counted (``skipped_elements``).
    LimitExceededError
    """
    data = bytes(data)
    arr = np.frombuffer(data, dtype=np.uint8)
    lines = split_lines(arr)
    n = arr.size
    first_byte = arr[np.minimum(lines.first, max(n - 1, 0))] if n else np.zeros(len(lines), np.uint8)
    content = np.flatnonzero(~lines.blank() & (first_byte != ord("#")))
    del first_byte
    if content.size == 0:
        raise MeshFormatError("empty OFF file")

    def tokens_of(i: int, lines: Lines = lines, content: np.ndarray = content) -> list[bytes]:
        li = int(content[i])
        return data[int(lines.first[li]) : int(lines.ends[li])].split(b"#", 1)[0].split()

    head = tokens_of(0)
    m = _header_keyword(head[0])
    if m is None:
        raise MeshFormatError("missing OFF header keyword", f"line {int(content[0]) + 1}")
    if m.group(4) or m.group(5):
        raise MeshFormatError("OFF variant of another dimension than 3 is not supported", "line 1")
    rest = head[1:]
    used = 1
    if rest and rest[0].upper() == b"BINARY":
        raise MeshFormatError("binary OFF is not supported", f"line {int(content[0]) + 1}")
    if not rest:
        if content.size < 2:
            raise MeshFormatError("missing OFF element counts")
        rest = tokens_of(1)
        used = 2
    counts_line = int(content[used - 1])
    counts = _ints(rest, counts_line)
    if len(counts) not in (2, 3) or min(counts) < 0:
        raise MeshFormatError("expected 'vertices faces [edges]' counts", f"line {counts_line + 1}")
    nv, nf = counts[0], counts[1]
    limits.check("vertices", nv)
    limits.check("faces", nf)
    body = content[used:]
    if body.size < nv + nf:
        raise MeshFormatError(
            f"file ends early: {nv} vertices and {nf} faces declared, {body.size} lines found"
        )
    vl, fl = body[:nv], body[nv : nv + nf]
    slot_lines = lines.starts[vl]
    v_begin, v_stop = lines.first[vl], lines.nexts[vl]
    f_begin, f_stop = lines.first[fl], lines.nexts[fl]
    del lines, content, body, tokens_of

    positions, decimals = parse_vertex_lines(arr, v_begin, v_stop, nv, vl)
    del v_begin, v_stop

    ftext = strip_comments(gather(arr, f_begin, f_stop))
    del f_begin, f_stop
    fb = parse_block(ftext, nf, np.float64, fl, what="face value")
    del ftext
    ncorner = fb.values[fb.offsets] if nf else np.zeros(0)
    bad = np.flatnonzero(
        (ncorner != np.floor(ncorner)) | (ncorner < 0) | (ncorner > fb.counts - 1)
    )
    if bad.size:
        raise MeshFormatError("bad face corner count", f"line {int(fl[bad[0]]) + 1}")
    ncorner = ncorner.astype(np.int64)
    limits.check("faces", int(np.maximum(ncorner - 2, 0).sum()))
    idx = ragged_take(fb.values, fb.offsets + 1, ncorner)
    badi = np.flatnonzero((idx != np.floor(idx)) | (idx < 0) | (idx >= nv))
    if badi.size:
        face = int(np.searchsorted(np.cumsum(ncorner), badi[0], side="right"))
        raise MeshFormatError("face vertex index out of range", f"line {int(fl[face]) + 1}")
    del fb
    triangles = triangulate(ncorner, idx.astype(np.int64))
    n_triangles = len(triangles)
    vertices, faces, slot_to_vertex = weld(positions, triangles, copy=False)  # both are temporaries
    doc = OffDocument(data, [MeshPart("mesh0", vertices, faces, slot_to_vertex)], slot_lines)
    doc.decimals = decimals
    # faces of fewer than 3 corners (points, edges) and triangles that repeat a corner: skipped
    doc.skipped_elements = int(np.count_nonzero(ncorner < 3)) + n_triangles - len(faces)
    return doc


SPEC = FormatSpec("off", "OFF", "OFF", ("off",), "application/off", sniff, read, sniff_rank=2)
