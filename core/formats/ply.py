"""Stanford PLY: ``ascii``, ``binary_little_endian`` and ``binary_big_endian``.

Any property types and any extra elements (before or after ``vertex``/``face``) are walked
over and kept byte for byte.  The ``vertex`` element needs float or double ``x``, ``y``,
``z`` (other vertex properties -- colour, normals, confidence, flags... -- are carried
through); the ``face`` element's ``vertex_indices`` (or ``vertex_index``) list may have any
count and index types, and faces may have other properties.  Polygons are fan-triangulated
for the engine.  A file without faces may give its triangles as strips instead
(a ``tristrips`` element, as range-scan tools and Stanford's older models write: each record a
list of vertex indices, ``-1`` -- or, unsigned, the type's largest value -- starting a new
strip).  ASCII files must hold one element record per line (as every writer does).

Declared counts are checked against :class:`Limits` and against the bytes (binary) or lines
(ASCII) actually present before anything proportional to them is allocated.

Write: ASCII -- only the moved vertices' lines change, and on them only the x, y, z tokens.
Binary -- the coordinate bytes of moved vertices are overwritten with values of the stored
type and byte order; nothing else changes.
"""

from __future__ import annotations

import struct
from array import array
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.errors import MeshFormatError
from core.formats._text import (
    TextMeshDocument,
    check_finite,
    decimals_of,
    moved_slots,
    parse_block,
    ragged_take,
    split_lines,
    triangulate,
)
from core.formats.base import FormatSpec, Limits, MeshPart, strip_triangles, weld

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_ENCODINGS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
#: element and property lines of one header (real files have tens; each costs Python work)
MAX_DECLARATIONS = 4096
_MAX_HEADER = 1 << 20


def sniff(data: bytes, name: str) -> bool:
    """True when ``data`` starts with the PLY magic line."""
    return data[:4] == b"ply\n" or data[:5] == b"ply\r\n"


@dataclass
class _Property:
    name: str
    type: str  # numpy code without byte order ("f4")
    count_type: str | None = None  # set for list properties

    @property
    def is_list(self) -> bool:
        return self.count_type is not None


@dataclass
class _Element:
    name: str
    count: int
    line: int
    props: list[_Property] = field(default_factory=list)
    positions: dict[str, int] = field(default_factory=dict)  # property name -> index

    def add(self, prop: _Property) -> bool:
        """Append ``prop``; False (and nothing added) when its name is already declared."""
        if prop.name in self.positions:  # a dict, not a search: 50k properties took 89 s
            return False
        self.positions[prop.name] = len(self.props)
        self.props.append(prop)
        return True

    def index(self, name: str) -> int | None:
        return self.positions.get(name)

    @property
    def label(self) -> str:
        """How messages name the element: its name only when it is one the reader knows (a name
        from the file is never echoed)."""
        return self.name if self.name in ("vertex", "face") else f"element of header line {self.line}"

    def min_size(self) -> int:
        """Smallest binary record (lists empty)."""
        return sum(np.dtype(p.count_type or p.type).itemsize for p in self.props)


def _parse_header(data: bytes) -> tuple[str, list[_Element], int]:
    """Encoding, elements and body offset."""
    end = -1
    search = 0
    while True:
        hit = data.find(b"\nend_header", search, _MAX_HEADER)
        if hit < 0:
            raise MeshFormatError("PLY header has no end_header line (within the first MiB)")
        nxt = data[hit + 11 : hit + 12]
        if nxt in (b"", b"\n", b"\r", b" ", b"\t"):
            end = hit + 1
            break
        search = hit + 1
    after = end + len(b"end_header")
    while after < len(data) and data[after : after + 1] in (b" ", b"\t"):
        after += 1
    if data[after : after + 2] == b"\r\n":
        body = after + 2
    elif data[after : after + 1] == b"\n":
        body = after + 1
    elif after == len(data):
        body = after
    else:
        raise MeshFormatError("PLY end_header not followed by a line break")
    text = data[:end].decode("latin-1")
    encoding = None
    elements: list[_Element] = []
    names: set[str] = set()
    declared = 0
    for i, raw in enumerate(text.split("\n")[1:], start=2):
        tokens = raw.split()
        if not tokens or tokens[0] in ("comment", "obj_info"):
            continue
        where = f"header line {i}"
        declared += 1
        if declared > MAX_DECLARATIONS:
            raise MeshFormatError(f"over {MAX_DECLARATIONS} elements and properties in the header", where)
        key = tokens[0]
        if key == "format":
            if len(tokens) != 3 or tokens[1] not in _ENCODINGS or encoding is not None:
                raise MeshFormatError("bad PLY format line", where)
            encoding = tokens[1]
        elif key == "element":
            if len(tokens) != 3 or not (tokens[2].isascii() and tokens[2].isdigit() and len(tokens[2]) < 19):
                raise MeshFormatError("bad PLY element line", where)
            if tokens[1] in names:
                raise MeshFormatError("PLY element declared twice", where)
            names.add(tokens[1])
            elements.append(_Element(tokens[1], int(tokens[2]), i))
        elif key == "property":
            if not elements:
                raise MeshFormatError("PLY property before any element", where)
            el = elements[-1]
            if len(tokens) == 3 and tokens[1] in _TYPES:
                prop = _Property(tokens[2], _TYPES[tokens[1]])
            elif (
                len(tokens) == 5 and tokens[1] == "list" and tokens[2] in _TYPES and tokens[3] in _TYPES
                and _TYPES[tokens[2]][0] in "iu"
            ):
                prop = _Property(tokens[4], _TYPES[tokens[3]], _TYPES[tokens[2]])
            else:
                raise MeshFormatError("bad PLY property line", where)
            if not el.add(prop):
                raise MeshFormatError("PLY property declared twice in one element", where)
        else:
            raise MeshFormatError("unknown PLY header keyword", where)
    if encoding is None:
        raise MeshFormatError("PLY header has no format line")
    return encoding, elements, body


class PlyDocument(TextMeshDocument):
    """A parsed PLY file (one part, ``"mesh0"``).

    Attributes
    ----------
    elements : list of (str, int)
        Every element of the header with its count, in file order.
    """

    format = "ply"

    def __init__(self, data: bytes, parts: list[MeshPart], encoding: str) -> None:
        super().__init__(data, parts)
        self.encoding = encoding
        self.elements: list[tuple[str, int]] = []
        # ASCII: line start and x/y/z token index of every vertex
        self._slot_lines = np.zeros(0, np.int64)
        self._slot_tokens = np.zeros(3, np.int64)
        # binary: vertex record runs (first vertex, byte offset, record size, x/y/z field offsets)
        # and the x/y/z dtypes (with byte order)
        self._runs = np.zeros((0, 6), np.int64)
        self._coord_dtypes: list[np.dtype] = []

    def quantize(self, vertices: np.ndarray, decimals: int | None = None) -> np.ndarray:
        """Positions as a :meth:`write` then a new read would give them back."""
        if self.encoding == "ascii":
            return super().quantize(vertices, decimals)
        v = np.asarray(vertices, dtype=np.float64)
        out = np.empty(v.shape, dtype=np.float64)
        for c, dt in enumerate(self._coord_dtypes):
            out[..., c] = v[..., c].astype(dt)
        return out

    def _patch(self, vertices: list[np.ndarray], moved: list[np.ndarray], decimals: int | None) -> bytes:
        if self.encoding == "ascii":
            return self._patch_text(vertices, moved, decimals, self._slot_lines, self._slot_tokens)
        part = self.parts[0]
        slots = moved_slots(part.slot_to_vertex, moved[0], len(part.vertices))
        if slots.size == 0:
            return self.data
        new = np.asarray(vertices[0], dtype=np.float64)[part.slot_to_vertex[slots]]
        run = self._runs[np.searchsorted(self._runs[:, 0], slots, side="right") - 1]
        record = run[:, 1] + (slots - run[:, 0]) * run[:, 2]
        out = np.frombuffer(bytearray(self.data), dtype=np.uint8)
        for c, dt in enumerate(self._coord_dtypes):
            raw = new[:, c].astype(dt).view(np.uint8).reshape(-1, dt.itemsize)
            out[(record + run[:, 3 + c])[:, None] + np.arange(dt.itemsize)] = raw
        return out.tobytes()


def read(data: bytes, limits: Limits, name: str = "ply") -> PlyDocument:
    """Parse a PLY file.

    Parameters
    ----------
    data : bytes
        The whole file.
    limits : Limits
        ``vertex`` and ``face`` counts are checked right after the header.
    name : str
        Format key (unused).

    Raises
    ------
    MeshFormatError
        Bad header, missing x/y/z, integer coordinates, counts larger than the bytes/lines
        present, non-numeric values, bad list counts, index out of range, NaN/Inf coordinate.
    LimitExceededError
    """
    data = bytes(data)
    encoding, elements, body = _parse_header(data)
    vertex = next((e for e in elements if e.name == "vertex"), None)
    face = next((e for e in elements if e.name == "face"), None)
    # no faces (no face element, or one of no records, as some writers declare beside their strips):
    # triangle strips, if the file has them
    strips = (face is None or face.count == 0) and any(e.name == "tristrips" for e in elements)
    if strips:
        face = next(e for e in elements if e.name == "tristrips")
    if vertex is None:
        raise MeshFormatError("PLY file has no vertex element")
    limits.check("vertices", vertex.count)
    if face is not None:
        limits.check("faces", face.count)
    if encoding != "ascii":
        # binary records whose list lengths vary are walked one by one: the records of every
        # element with a list, other than the vertices, count against the faces limit
        listed = sum(e.count for e in elements if e is not vertex and any(p.is_list for p in e.props))
        limits.check("faces", listed)
    coord = [vertex.index(c) for c in "xyz"]
    if any(i is None or vertex.props[i].is_list for i in coord):
        raise MeshFormatError("PLY vertex element lacks scalar x, y and z properties")
    coord_idx = [int(i) for i in coord if i is not None]
    ctypes = [vertex.props[i].type for i in coord_idx]
    if any(t[0] != "f" for t in ctypes):
        raise MeshFormatError("PLY vertex coordinates must be float or double")
    index_prop = None
    if face is not None:
        for nm in ("vertex_indices", "vertex_index"):
            k = face.index(nm)
            if k is not None and face.props[k].is_list:
                index_prop = k
                break
        if index_prop is not None and face.props[index_prop].type[0] == "f":
            raise MeshFormatError("PLY face vertex indices must be integers")
    doc = PlyDocument(data, [], encoding)
    doc.elements = [(e.name, e.count) for e in elements]
    # a strip ends at -1, or, with unsigned indices, at the type's largest value (OpenGL's restart index)
    restart = None
    if strips and face is not None and index_prop is not None:
        code = face.props[index_prop].type
        restart = int(np.iinfo(code).max) if code[0] == "u" else -1
    if encoding == "ascii":
        positions, counts, flat = _read_ascii(doc, elements, vertex, face, coord_idx, index_prop, body,
                                              restart)
    else:
        positions, counts, flat = _read_binary(
            doc, elements, vertex, face, coord_idx, index_prop, body, _ENCODINGS[encoding]
        )
        doc._coord_dtypes = [np.dtype(_ENCODINGS[encoding] + t) for t in ctypes]
        if len(set(ctypes)) == 1:
            doc.storage_dtype = np.dtype(ctypes[0])
    check_finite(positions)
    limits.check("faces", int(np.maximum(counts - 2, 0).sum()) if counts.size else 0)
    flat = np.asarray(flat, dtype=np.int64)
    if restart is not None and restart >= 0:
        flat[flat == restart] = -1
    lowest = -1 if strips else 0  # (a strip's -1 starts the next one)
    if flat.size and (flat.min() < lowest or flat.max() >= vertex.count):
        assert face is not None
        bad = int(np.flatnonzero((flat < lowest) | (flat >= vertex.count))[0])
        face_no = int(np.searchsorted(np.cumsum(counts), bad, side="right"))
        raise MeshFormatError("face vertex index out of range", f"{face.name} {face_no}")
    joins = 0
    if strips:
        counts, flat, joins = strip_triangles(counts, flat)
    triangles = triangulate(counts, flat)
    del flat
    n_triangles = len(triangles)
    vertices, faces, slot_to_vertex = weld(positions, triangles, copy=False)  # both are temporaries
    doc.parts = [MeshPart("mesh0", vertices, faces, slot_to_vertex)]
    # faces of fewer than 3 corners, and triangles that repeat a corner, are skipped (a strip's
    # repeated corners that join it to the next piece are how strips are written: not counted)
    doc.skipped_elements = int(np.count_nonzero(counts < 3)) + n_triangles - len(faces) - joins
    return doc


def _check_counts(n: np.ndarray, room: np.ndarray, where: np.ndarray) -> None:
    """ASCII list counts must be whole, >= 0 and fit the record (``room`` values left).

    ``where`` is the 1-based file line of every record.
    """
    bad = (n != np.floor(n)) | (n < 0) | (n > room)
    if bad.any():
        raise MeshFormatError("bad PLY list count", f"line {int(where[np.argmax(bad)])}")


def _read_ascii(
    doc: PlyDocument, elements: list[_Element], vertex: _Element, face: _Element | None,
    coord_idx: list[int], index_prop: int | None, body: int, restart: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``restart``: in strips, the index that starts the next strip (kept; :func:`read` makes it -1)."""
    data = doc.data
    arr = np.frombuffer(data, dtype=np.uint8)
    lines = split_lines(arr, body)
    records = np.flatnonzero(~lines.blank())
    needed = sum(e.count for e in elements if e.props)
    if needed > records.size:
        raise MeshFormatError(
            f"file ends early: {needed} element records declared, {records.size} lines found"
        )
    # each element's lines and the bytes holding them; then the line table can go
    plan: list[tuple[_Element, np.ndarray, int, int]] = []
    cursor = 0
    for el in elements:
        if not el.props or el.count == 0:
            continue
        ln = records[cursor : cursor + el.count]
        cursor += el.count
        plan.append((el, ln, int(lines.starts[ln[0]]), int(lines.nexts[ln[-1]])))
        if el is vertex:
            doc._slot_lines = lines.starts[ln]
    del lines, records
    base = data.count(b"\n", 0, body)  # file line of the first body line
    positions = np.zeros((0, 3))
    counts = np.zeros(0, np.int64)
    flat = np.zeros(0, np.int64)
    for el, ln, begin, stop in plan:
        lo, hi = int(ln[0]), int(ln[-1])
        is_vertex = el is vertex
        block = parse_block(
            data[begin:stop], hi - lo + 1, np.float64, np.arange(lo, hi + 1) + base,
            spans=is_vertex, what=f"{el.label} value",
        )
        where = ln + base + 1
        ntok = block.counts[ln - lo]
        first_tok = block.offsets[ln - lo]
        end_tok = first_tok + ntok
        o = first_tok.copy()
        cols: dict[int, np.ndarray] = {}
        lists: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for k, p in enumerate(el.props):
            short = o >= end_tok
            if short.any():
                line = int(where[np.argmax(short)])
                raise MeshFormatError(f"too few values for {el.label}", f"line {line}")
            if p.is_list:
                n = block.values[o]
                room = end_tok - o - 1
                _check_counts(n, room, where)
                n = n.astype(np.int64)
                lists[k] = (n, o + 1)
                o = o + 1 + n
            else:
                cols[k] = o
                o = o + 1
        extra = o != end_tok
        if extra.any():
            raise MeshFormatError(f"too many values for {el.label}", f"line {int(where[np.argmax(extra)])}")
        if is_vertex:
            tok = np.stack([cols[i] for i in coord_idx], axis=1)
            positions = block.values[tok]
            assert block.tok_starts is not None and block.tok_ends is not None
            doc.decimals = decimals_of(block.text, block.tok_starts[tok], block.tok_ends[tok])
            rel = tok - first_tok[:, None]
            doc._slot_tokens = rel[0] if np.all(rel == rel[0]) else rel
        elif el is face and index_prop is not None:
            n, start = lists[index_prop]
            vals = ragged_take(block.values, start, n)
            index = (vals >= 0) & (vals < vertex.count)
            if restart is not None:
                index |= vals == restart
            bad = (vals != np.floor(vals)) | ~index
            if bad.any():
                face_no = int(np.searchsorted(np.cumsum(n), int(np.argmax(bad)), side="right"))
                raise MeshFormatError("bad face vertex index", f"line {int(where[face_no])}")
            counts, flat = n, vals.astype(np.int64)
        del block, cols, lists
    return positions, counts, flat


def _record_dtype(props: list[_Property], endian: str, lens: tuple[int, ...]) -> np.dtype:
    """Binary record dtype with every list of the given length (fields ``p{k}``/``n{k}``)."""
    fields: list[tuple[str, str] | tuple[str, str, tuple[int]]] = []
    li = 0
    for k, p in enumerate(props):
        if p.is_list:
            assert p.count_type is not None
            fields.append((f"n{k}", endian + p.count_type))
            if lens[li]:
                fields.append((f"p{k}", endian + p.type, (lens[li],)))
            li += 1
        else:
            fields.append((f"p{k}", endian + p.type))
    return np.dtype(fields)


def _check_room(data: bytes, pos: int, el: _Element) -> None:
    """The declared record count must fit in the bytes left (checked before allocating)."""
    need = el.count * el.min_size()
    if need > len(data) - pos:
        raise MeshFormatError(
            f"file ends early: {el.count} {el.label} records need at least {need} bytes, "
            f"{len(data) - pos} left", f"byte {pos}"
        )


#: runs of equal list lengths shorter than this are scanned record by record instead
_MIN_RUN = 32
#: a scanned batch stops after this many records or this many bytes of records
_SCAN_RECORDS = 4096
_SCAN_BYTES = 1 << 20
#: a record longer than this is read as a run of its own (never gathered byte by byte)
_BIG_RECORD = 1 << 16
_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}


@dataclass
class _Batch:
    """Consecutive records of varying list lengths, scanned one by one."""

    first: int  # index of the first record in its element
    offsets: np.ndarray  # (m,) int64 byte offset of every record
    lens: np.ndarray  # (m, number of list properties) int64 list lengths
    end: int  # byte offset after the last record


def _scan_plan(props: list[_Property], endian: str) -> tuple[list[tuple[int, Any, int, int]], int]:
    """Per list property: (fixed bytes before its count, count reader, count size, item size);
    then the fixed bytes after the last list."""
    plan: list[tuple[int, Any, int, int]] = []
    fixed = 0
    for p in props:
        if p.is_list:
            assert p.count_type is not None
            count = struct.Struct(endian + _STRUCT_CODES[p.count_type])
            plan.append((fixed, count.unpack_from, count.size, np.dtype(p.type).itemsize))
            fixed = 0
        else:
            fixed += np.dtype(p.type).itemsize
    return plan, fixed


def _scan(data: bytes, pos: int, el: _Element, plan: list[tuple[int, Any, int, int]], tail: int,
          first: int) -> _Batch:
    """Walk records from ``pos`` one by one (a tight loop, no numpy call per record), up to
    :data:`_SCAN_RECORDS` records or :data:`_SCAN_BYTES` bytes, stopping before a record longer
    than :data:`_BIG_RECORD` (the first record must not be one)."""
    size = len(data)
    offsets, lens = array("q"), array("q")
    add_offset, add_len = offsets.append, lens.append
    n_lists = len(plan)
    limit = min(_SCAN_RECORDS, el.count - first)
    start = pos
    k = 0
    while k < limit:
        o = pos
        for skip, unpack, csize, isize in plan:
            o += skip
            if o + csize > size:
                raise MeshFormatError(f"file ends inside {el.label} record {first + k}", f"byte {o}")
            n = unpack(data, o)[0]
            if n < 0:
                raise MeshFormatError(f"negative list count in {el.label} record {first + k}", f"byte {o}")
            add_len(n)
            o += csize + n * isize
        o += tail
        if o > size:
            raise MeshFormatError(f"file ends inside {el.label} record {first + k}", f"byte {pos}")
        if k and o - pos > _BIG_RECORD:
            del lens[len(lens) - n_lists :]
            break
        add_offset(pos)
        pos = o
        k += 1
        if pos - start >= _SCAN_BYTES:
            break
    return _Batch(
        first,
        np.frombuffer(offsets, dtype=np.int64),
        np.frombuffer(lens, dtype=np.int64).reshape(k, n_lists),
        pos,
    )


def _runs(
    data: bytes, pos: int, el: _Element, endian: str
) -> Iterator[tuple[int, int, np.ndarray] | _Batch]:
    """Walk a binary element: yields ``(first record, byte offset, records)`` runs of records
    sharing the same list lengths (one run for fixed-size records), and :class:`_Batch` es of
    records whose list lengths vary (mixed triangles and quads...).  Ends at the element end.
    """
    size = len(data)
    _check_room(data, pos, el)
    if not any(p.is_list for p in el.props):
        dt = _record_dtype(el.props, endian, ())
        yield 0, pos, np.frombuffer(data, dtype=dt, count=el.count, offset=pos)
        return
    list_ks = [k for k, p in enumerate(el.props) if p.is_list]
    plan, tail = _scan_plan(el.props, endian)
    cache: dict[tuple[int, ...], np.dtype] = {}
    done, window = 0, 64
    while done < el.count:
        # list lengths of the record at pos
        lens = []
        off = pos
        for p in el.props:
            if p.is_list:
                assert p.count_type is not None
                cdt = np.dtype(endian + p.count_type)
                if off + cdt.itemsize > size:
                    raise MeshFormatError(f"file ends inside {el.label} record {done}", f"byte {off}")
                n = int(np.frombuffer(data, dtype=cdt, count=1, offset=off)[0])
                if n < 0:
                    raise MeshFormatError(f"negative list count in {el.label} record {done}", f"byte {off}")
                lens.append(n)
                off += cdt.itemsize + n * np.dtype(p.type).itemsize
            else:
                off += np.dtype(p.type).itemsize
        if off > size:
            raise MeshFormatError(f"file ends inside {el.label} record {done}", f"byte {pos}")
        key = tuple(lens)
        if key not in cache:
            cache[key] = _record_dtype(el.props, endian, key)
        dt = cache[key]
        m = min(window, el.count - done, (size - pos) // dt.itemsize)
        recs = np.frombuffer(data, dtype=dt, count=m, offset=pos)
        same = np.ones(m, dtype=bool)
        for k, n in zip(list_ks, lens, strict=True):
            same &= recs[f"n{k}"] == n
        j = m if same.all() else int(np.argmin(same))
        if j < min(_MIN_RUN, el.count - done) and off - pos <= _BIG_RECORD:
            # lengths vary from record to record: numpy calls per short run would cost far more
            # than scanning the records one by one
            batch = _scan(data, pos, el, plan, tail, done)
            yield batch
            done += len(batch.offsets)
            pos = batch.end
            window = 64
            continue
        yield done, pos, recs[:j]
        done += j
        pos += j * dt.itemsize
        window = min(window * 2, 1 << 20) if j == m else 64


def _field_offsets(props: list[_Property], lens: np.ndarray, wanted: list[int]) -> dict[int, np.ndarray]:
    """Byte offset, inside each record of a batch, of the properties ``wanted`` (a list's count)."""
    at = np.zeros(len(lens), dtype=np.int64)
    out: dict[int, np.ndarray] = {}
    li = 0
    for k, p in enumerate(props):
        if k in wanted:
            out[k] = at.copy()
        if p.is_list:
            assert p.count_type is not None
            at += np.dtype(p.count_type).itemsize + lens[:, li] * np.dtype(p.type).itemsize
            li += 1
        else:
            at += np.dtype(p.type).itemsize
    return out


def _gather(data: bytes, offsets: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """One value of ``dtype`` at each byte offset."""
    raw = np.frombuffer(data, dtype=np.uint8)[offsets[:, None] + np.arange(dtype.itemsize)]
    return raw.view(dtype).reshape(-1)


def _gather_lists(data: bytes, starts: np.ndarray, lens: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """The ``lens[i]`` values of ``dtype`` from byte ``starts[i]`` on, all lists one after another."""
    total = int(lens.sum())
    if total == 0:
        return np.zeros(0, dtype=dtype)
    rec = np.repeat(np.arange(len(lens)), lens)
    j = np.arange(total) - np.repeat(np.cumsum(lens) - lens, lens)
    return _gather(data, starts[rec] + j * dtype.itemsize, dtype)


def _read_binary(
    doc: PlyDocument, elements: list[_Element], vertex: _Element, face: _Element | None,
    coord_idx: list[int], index_prop: int | None, body: int, endian: str,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    data = doc.data
    pos = body
    positions = np.zeros((0, 3))
    runs: list[np.ndarray] = []
    counts_l: list[np.ndarray] = []
    flat_l: list[np.ndarray] = []
    for el in elements:
        if not el.props or el.count == 0:
            continue
        is_vertex, is_face = el is vertex, el is face and index_prop is not None
        if is_vertex:
            _check_room(data, pos, el)
            positions = np.empty((el.count, 3))
        for item in _runs(data, pos, el, endian):
            if isinstance(item, _Batch):
                first, m = item.first, len(item.offsets)
                if is_vertex:
                    rel = _field_offsets(el.props, item.lens, coord_idx)
                    with np.errstate(invalid="ignore"):  # signalling NaNs; refused after the walk
                        for c, k in enumerate(coord_idx):
                            dt = np.dtype(endian + el.props[k].type)
                            positions[first : first + m, c] = _gather(data, item.offsets + rel[k], dt)
                    # one run per record: (first, offset, size unused, x/y/z offsets in the record)
                    runs.append(
                        np.stack(
                            [first + np.arange(m), item.offsets, np.zeros(m, np.int64)]
                            + [rel[k] for k in coord_idx],
                            axis=1,
                        )
                    )
                elif is_face:
                    assert index_prop is not None
                    prop = el.props[index_prop]
                    assert prop.count_type is not None
                    li = sum(1 for p in el.props[:index_prop] if p.is_list)
                    lens = item.lens[:, li]
                    starts = item.offsets + _field_offsets(el.props, item.lens, [index_prop])[index_prop]
                    starts += np.dtype(prop.count_type).itemsize
                    counts_l.append(lens.copy())
                    values = _gather_lists(data, starts, lens, np.dtype(endian + prop.type))
                    flat_l.append(values.astype(np.int64))
                pos = item.end
                continue
            first, off, recs = item
            m = recs.size
            if is_vertex:
                dt = recs.dtype
                fields = dt.fields
                assert fields is not None
                runs.append(
                    np.array([[first, off, dt.itemsize] + [int(fields[f"p{k}"][1]) for k in coord_idx]])
                )
                with np.errstate(invalid="ignore"):  # signalling NaNs; refused after the walk
                    for c, k in enumerate(coord_idx):
                        positions[first : first + m, c] = recs[f"p{k}"]
            elif is_face:
                n = int(recs[f"n{index_prop}"][0]) if m else 0
                counts_l.append(np.full(m, n, np.int64))
                if n:  # astype first: one int64 copy of the strided field, then a free reshape
                    flat_l.append(recs[f"p{index_prop}"].astype(np.int64).reshape(-1))
            pos = off + m * recs.dtype.itemsize
    doc._runs = np.concatenate(runs).astype(np.int64) if runs else np.zeros((0, 6), np.int64)
    counts = counts_l[0] if len(counts_l) == 1 else np.concatenate(counts_l or [np.zeros(0, np.int64)])
    flat = flat_l[0] if len(flat_l) == 1 else np.concatenate(flat_l or [np.zeros(0, np.int64)])
    del counts_l, flat_l
    return positions, counts, flat


SPEC = FormatSpec("ply", "PLY", "PLY", ("ply",), "application/x-ply", sniff, read)
