"""Wavefront OBJ (text).

Read: ``v`` lines (x y z, then optional w or colour components), ``f`` lines with any corner
form (``1``, ``1/2``, ``1//3``, ``1/2/3``, negative = relative to the ``v`` lines read so far),
polygons fan-triangulated; faces of fewer than 3 distinct corners and ``l``/``p`` elements
are skipped (counted in ``skipped_elements``) and kept as text.
``vt``/``vn``/``o``/``g``/``s``/``mtllib``/``usemtl``, comments and any other statement are kept
as text and never interpreted (material libraries are never opened).  The whole file is one
part, named after its first ``o`` statement (else ``"mesh0"``).

Write: only the ``v`` lines of moved vertices change, and on them only the x, y, z tokens.
"""

from __future__ import annotations

import re

import numpy as np

from core.errors import MeshFormatError
from core.formats._text import (
    BOM,
    TextMeshDocument,
    gather,
    keyword_mask,
    parse_block,
    parse_vertex_lines,
    split_lines,
    strip_comments,
    sub_lines,
    triangulate,
)
from core.formats.base import FormatSpec, Limits, MeshPart, weld

#: statements that may start an OBJ file (for sniffing)
_KEYWORDS = {
    b"v", b"vt", b"vn", b"vp", b"f", b"l", b"p", b"o", b"g", b"s", b"mtllib", b"usemtl", b"usemap",
    b"maplib", b"cstype", b"deg", b"bmat", b"step", b"curv", b"curv2", b"surf", b"parm", b"trim",
    b"hole", b"scrv", b"sp", b"end", b"con", b"mg", b"lod", b"bevel", b"c_interp", b"d_interp",
    b"shadow_obj", b"trace_obj", b"ctech", b"stech",
}
_SNIFF_BYTES = 64 * 1024
_CORNER_SUFFIX = re.compile(rb"(?<=\S)/\S*")


def sniff(data: bytes, name: str) -> bool:
    """True when the first statements of ``data`` (skipping comments and blank lines) are OBJ."""
    head = bytes(data[:_SNIFF_BYTES]).removeprefix(BOM)
    if not head or b"\x00" in head:
        return False
    lines = head.split(b"\n")
    if len(head) == _SNIFF_BYTES and len(lines) > 1:
        lines = lines[:-1]  # last line may be cut
    seen = 0
    geometry = False
    for line in lines:
        tokens = line.split(None, 1)
        if not tokens or tokens[0].startswith(b"#"):
            continue
        if tokens[0] not in _KEYWORDS:
            return False
        geometry |= tokens[0] in (b"v", b"f", b"o", b"g", b"mtllib", b"usemtl")
        seen += 1
        if seen >= 16:
            break
    return geometry


class ObjDocument(TextMeshDocument):
    """A parsed OBJ file.

    Attributes
    ----------
    mtllibs : list of str
        Material libraries named by ``mtllib`` statements (kept as text, never opened).
    """

    format = "obj"
    encoding = "ascii"

    def __init__(
        self, data: bytes, parts: list[MeshPart], slot_lines: np.ndarray, mtllibs: list[str]
    ) -> None:
        super().__init__(data, parts)
        self._slot_lines = slot_lines
        self.mtllibs = mtllibs

    def _patch(self, vertices: list[np.ndarray], moved: list[np.ndarray], decimals: int | None) -> bytes:
        return self._patch_text(vertices, moved, decimals, self._slot_lines, np.array([1, 2, 3]))


def _line_text(data: bytes, start: int, end: int) -> str:
    return data[start:end].split(b"#", 1)[0].strip().decode("utf-8", "replace")


def read(data: bytes, limits: Limits, name: str = "obj") -> ObjDocument:
    """Parse an OBJ file.

    Parameters
    ----------
    data : bytes
        The whole file.
    limits : Limits
        Vertex and triangle counts are checked before the numbers are converted.
    name : str
        Format key (unused).

    Raises
    ------
    MeshFormatError
        Non-numeric coordinate or index, fewer than 3 coordinates, index 0 or out of range,
        NaN/Inf coordinate.  Faces of fewer than 3 (distinct) corners and ``l``/``p`` lines are
        skipped and counted (:attr:`~core.formats.base.MeshDocument.skipped_elements`).
    LimitExceededError
    """
    data = bytes(data)
    arr = np.frombuffer(data, dtype=np.uint8)
    lines = split_lines(arr)
    vl = np.flatnonzero(keyword_mask(arr, lines, b"v"))
    fl = np.flatnonzero(keyword_mask(arr, lines, b"f"))
    n_lines = int(np.count_nonzero(keyword_mask(arr, lines, b"l") | keyword_mask(arr, lines, b"p")))
    limits.check("vertices", int(vl.size))
    limits.check("faces", int(fl.size))  # face lines, before tokenising (skipped short ones cost as much)
    part_name = ""
    o_lines = np.flatnonzero(keyword_mask(arr, lines, b"o"))
    if o_lines.size:
        i = int(o_lines[0])
        part_name = _line_text(data, int(lines.first[i]) + 1, int(lines.ends[i]))
    mtllibs = [
        _line_text(data, int(lines.first[i]) + 6, int(lines.ends[i]))
        for i in np.flatnonzero(keyword_mask(arr, lines, b"mtllib"))[:64].tolist()
    ]
    slot_lines = lines.starts[vl]
    v_begin, v_stop = lines.first[vl] + 1, lines.nexts[vl]
    f_begin, f_stop = lines.first[fl] + 1, lines.nexts[fl]
    del lines

    # vertices: the numbers after "v", x y z first
    positions, decimals = parse_vertex_lines(arr, v_begin, v_stop, int(vl.size), vl)
    del v_begin, v_stop

    # faces: the vertex index of every corner ("i", "i/t", "i//n", "i/t/n")
    ftext = strip_comments(gather(arr, f_begin, f_stop))
    del f_begin, f_stop
    if b"/" in ftext:
        ftext = sub_lines(_CORNER_SUFFIX, ftext, 1 << 16)
    fblock = parse_block(ftext, int(fl.size), np.int64, fl, what="face vertex index")
    del ftext
    counts = fblock.counts
    short = int(np.count_nonzero(counts < 3))  # points and edges written as faces: skipped
    limits.check("faces", int(np.maximum(counts - 2, 0).sum()))
    idx = fblock.values
    del fblock
    # v lines before each face line, for relative (negative) indices
    before = np.repeat(np.searchsorted(vl, fl), counts)
    idx = np.where(idx < 0, idx + before, idx - 1)
    bad = np.flatnonzero((idx < 0) | (idx >= vl.size))
    if bad.size:
        face_line = fl[np.searchsorted(np.cumsum(counts), bad[0], side="right")]
        raise MeshFormatError("face vertex index out of range", f"line {int(face_line) + 1}")
    del before, bad
    triangles = triangulate(counts, idx)
    del idx
    n_triangles = len(triangles)
    vertices, faces, slot_to_vertex = weld(positions, triangles, copy=False)  # both are temporaries

    part = MeshPart(part_name or "mesh0", vertices, faces, slot_to_vertex)
    doc = ObjDocument(data, [part], slot_lines, mtllibs)
    doc.decimals = decimals
    doc.skipped_elements = short + n_lines + n_triangles - len(faces)
    return doc


SPEC = FormatSpec("obj", "OBJ", "OBJ", ("obj",), "model/obj", sniff, read, sniff_rank=3)
