"""glTF 2.0 meshes, binary (``.glb``) and JSON (``.gltf`` with embedded ``data:`` buffers).

What is read
------------
Every mesh primitive of mode TRIANGLES (4, the default), TRIANGLE_STRIP (5) or TRIANGLE_FAN (6),
indexed (UNSIGNED_BYTE/SHORT/INT) or not, with a VEC3 ``POSITION`` accessor: FLOAT, or
(KHR_mesh_quantization) BYTE/UNSIGNED_BYTE/SHORT/UNSIGNED_SHORT normalized or not, plain or
sparse, in a plain or meshopt-compressed bufferView, or a KHR_draco_mesh_compression primitive.
Strips and fans are converted to triangles for the engine; POINTS and LINES primitives (modes
0-3) are skipped and counted.  One :class:`MeshPart` per glTF *mesh*
(name from ``mesh.name`` or ``"mesh{i}"``) combines its triangle primitives; positions are welded
bit-exactly within the mesh (UV seams, split normals), and ``slot_to_vertex`` lists every
``POSITION`` element of every triangle primitive of the mesh, primitive after primitive (an
accessor shared by several primitives of the mesh once).  Meshes reusing each other's positions
may ask for at most :data:`MAX_REUSE` times the work the file's bytes hold (a Draco stream's first
decode at :data:`DRACO_DENSITY` times less: it holds far more than 12 bytes a slot would).

Nodes are ignored: the engine works on each mesh's *local* coordinates, so a mesh placed by
several nodes (instancing) is one part, and the watermark moves every instance the same way.

What is refused
---------------
Buffers whose URI is not an embedded ``data:...;base64,`` URI (relative or absolute paths,
``file:``, ``http(s):``...) are refused and never opened.  Image URIs are never looked at.
Positions may be quantized (KHR_mesh_quantization), sparse, meshopt- or Draco-compressed
(``gltf_accessors.py``, ``gltf_codecs.py``; compressed streams checked against the limits
before decoding).  Every count, offset and stride is checked against its bufferView and buffer
before anything is allocated, and JSON deeper than :data:`MAX_JSON_DEPTH` is refused before
parsing.

Writing
-------
Moved coordinates are patched in place in their accessor's encoding (float32 or the quantized
integer type) in their buffer: the GLB ``BIN`` chunk, or the re-encoded base64 payload of a
``data:`` URI; compressed streams that hold moved positions are re-encoded, spliced into their
buffer, and then the JSON is serialised again (:meth:`GltfDocument._reencode`).  Otherwise the
JSON text is kept byte for byte except the ``min``/``max`` arrays of ``POSITION`` accessors
whose extents changed (and re-encoded ``data:`` URIs), which are rewritten in place; for GLB the
JSON chunk is re-padded with spaces to 4 bytes and the chunk and total lengths are updated.  A
position element used by several meshes (the same bytes reached through two accessors) is
written once, from the first part that uses it.
"""

from __future__ import annotations

import base64
import binascii
import json
import re
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.errors import DegenerateMeshError, LimitExceededError, MeshFormatError
from core.formats._binary import finite_float64, moved_slots, patch_xyz
from core.formats.base import FormatSpec, Limits, MeshDocument, MeshPart, strip_triangles, weld
from core.formats.gltf_accessors import FLOAT, POSITION_DTYPES, Encoding
from core.formats.gltf_codecs import (
    DRACO_EXTENSION,
    MESHOPT_EXTENSIONS,
    DracoGrid,
    decode_draco,
    decode_meshopt,
    draco_grid,
    encode_draco,
    encode_meshopt,
    meshopt_view,
)

GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
#: Deepest JSON nesting accepted (real glTF files need about 8).
MAX_JSON_DEPTH = 64

_INDEX_DTYPES: dict[int, np.dtype] = {5121: np.dtype("<u1"), 5123: np.dtype("<u2"), 5125: np.dtype("<u4")}
_TRIANGLE_MODES = (4, 5, 6)
_SKIPPED_MODES = (0, 1, 2, 3)
#: Slots and faces of all meshes together may be this many times the file's bytes / 12 (one
#: float32 triple), plus :data:`REUSE_ALLOWANCE`: meshes and primitives may share data, not
#: multiply the work a file asks for.
MAX_REUSE = 8
REUSE_ALLOWANCE = 1 << 16
#: work units of one triangle primitive (its Python bookkeeping costs as much as ~1000 slots)
PRIMITIVE_WORK = 1024
#: the slots and faces a Draco stream decodes to, the first time it is decoded, count this many
#: times less: Draco stores them far below 12 bytes a slot (the horse, 48,485 vertices and 96,966
#: faces at 14-bit quantisation, in a 117 KB GLB: 1.25 units of work a byte where the rule above
#: allows 0.67, so MeshMark refused its own Draco output; a smooth 300 x 300 grid at Draco's
#: compression level 10: 7.7). A stream decoded again (another primitive pointing at its
#: bufferView) counts in full; the vertex and face limits bound a first decode in any case.
DRACO_DENSITY = 16
_KEY_SHIFT = 40  # (buffer << 40) | byte offset identifies a stored position element
#: buffer ids from here on are not buffers of the file: decoded meshopt views (+ view index),
#: decoded Draco positions (+ 2**20 + primitive number) and positions with no storage at all
#: (a sparse accessor's implicit zeros, ``UNSTORED``)
VIRTUAL = 1 << 24
_DRACO = VIRTUAL + (1 << 20)
UNSTORED = VIRTUAL + (1 << 22)

# a JSON string literal, or an unterminated one up to the end of the text: always matches at its
# first quote, so that scanning is linear even when the string never closes (an unclosed string
# of escaped quotes made the strict pattern retry at every quote: quadratic)
_STRING_RE = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*(?:"|\\?\Z)', re.DOTALL)
# an embedded data: URI string, up to its closing quote (base64 has no quote)
_DATA_URI_RE = re.compile(rb'"[dD][aA][tT][aA]:[^"]*"')
# string literals, other scalars (numbers, true, false, null) and structural characters
_TOKEN_RE = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"|[{}\[\]:,]|[^\s{}\[\]:,"]+')
_ASSET_RE = re.compile(rb'"asset"\s*:')
_WS = b" \t\r\n"


def sniff(data: bytes, name: str) -> bool:
    """``"glb"``: starts with the GLB magic; ``"gltf"``: a JSON object with an ``"asset"`` member."""
    if name == "glb":
        return data[:4] == GLB_MAGIC
    head = data[:64].lstrip(_WS)
    if head.startswith(b"\xef\xbb\xbf"):
        head = head[3:].lstrip(_WS)
    if not head.startswith(b"{"):
        return False
    # "asset" comes first in files from common exporters; look further only when it does not
    return _ASSET_RE.search(data, 0, 1 << 16) is not None or _ASSET_RE.search(data) is not None


def read(data: bytes, limits: Limits, name: str) -> MeshDocument:
    """Parse a GLB (``name="glb"``) or ``.gltf`` JSON (``name="gltf"``) file.

    Parameters
    ----------
    data : bytes
        The whole file.
    limits : Limits
        Checked before allocations proportional to declared counts.
    name : str
        Format key, ``"glb"`` or ``"gltf"``.

    Returns
    -------
    GltfDocument

    Raises
    ------
    MeshFormatError
        Malformed or unsupported content (external buffers, sparse or compressed positions...).
    LimitExceededError
        JSON, buffers, vertices, faces or meshes above ``limits``.
    DegenerateMeshError
        No triangle mesh in the file.
    """
    if data[:4] == GLB_MAGIC:
        return _Reader(data, limits).read_glb()
    return _Reader(data, limits).read_gltf()


class GltfDocument(MeshDocument):
    """A parsed glTF file; :meth:`write` patches positions in their buffers, in their encoding."""

    encoding = "binary"
    media_type = "model/gltf-binary"
    extension = "glb"
    storage_dtype: np.dtype | None = np.dtype(np.float32)

    def __init__(
        self,
        data: bytes,
        parts: list[MeshPart],
        *,
        gltf: dict[str, Any],
        text: str,
        json_chunk: tuple[int, int] | None,
        buffers: dict[int, tuple[bytes, int | None, str | None]],
        slots: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
        positions: dict[int, tuple[np.ndarray, np.ndarray, int]],
        encodings: list[Encoding],
        meshopt: dict[int, Any],
        draco: list[_DracoPrimitive],
        skipped: int = 0,
    ) -> None:
        super().__init__(data, parts)
        self.skipped_elements = skipped
        self.format = "gltf" if json_chunk is None else "glb"
        if json_chunk is None:
            self.encoding, self.media_type, self.extension = "ascii", "model/gltf+json", "gltf"
        self._gltf = gltf
        self._text = text
        self._json_chunk = json_chunk
        self._buffers = buffers
        self._slots = slots
        self._positions = positions
        self._encodings = encodings
        self._meshopt = meshopt
        self._draco = draco
        #: position encodings of the file, e.g. ``["float32"]``, ``["uint16", "meshopt"]``
        plain = {_encoding_name(encodings[e]) for _, _, e in positions.values()
                 if not isinstance(encodings[e], DracoGrid)}
        self.encodings = sorted(plain | ({"meshopt"} if meshopt else set()) | ({"draco"} if draco else set()))
        if encodings and any(not e.is_float for e in encodings):
            self.storage_dtype = None
        # per part and welded vertex, the encoding its stored slots share (-1: no single one, or
        # not writable), for quantize_part
        self._vertex_encoding = []
        self._draco_pins: list[np.ndarray] = []
        for part, (bufs, offs, enc, _) in zip(parts, slots, strict=True):
            code = np.where(bufs >= UNSTORED, -1, enc)
            if draco:  # Draco positions whose grid could not be recovered cannot be re-encoded
                gridded = np.array([isinstance(e, DracoGrid) for e in encodings])
                code = np.where((bufs >= _DRACO) & (bufs < UNSTORED) & ~gridded[enc], -1, code)
            lo = np.full(len(part.vertices), np.iinfo(np.int64).max)
            hi = np.full(len(part.vertices), -1)
            np.minimum.at(lo, part.slot_to_vertex, code)
            np.maximum.at(hi, part.slot_to_vertex, code)
            vertex_code = np.where(lo == hi, lo, -1)
            if draco:
                # a vertex on the seam of Draco primitives is stored on each primitive's grid and
                # read back at its first slot's (_draco_seams): it moves on that grid
                on_grid = (bufs >= _DRACO) & (bufs < UNSTORED) & (code >= 0)
                all_grid = np.ones(len(part.vertices), bool)
                np.logical_and.at(all_grid, part.slot_to_vertex, on_grid)
                first = np.full(len(part.vertices), len(bufs))
                np.minimum.at(first, part.slot_to_vertex, np.arange(len(bufs)))
                seam = (lo != hi) & all_grid & (first < len(bufs))
                vertex_code[seam] = code[first[seam]]
            self._vertex_encoding.append(vertex_code)
            pins = self._grid_pins(part, bufs, offs, enc) if draco else np.zeros(0, np.int64)
            self._draco_pins.append(pins)

    def _grid_pins(self, part: MeshPart, bufs: np.ndarray, offs: np.ndarray, enc: np.ndarray) -> np.ndarray:
        """Welded vertices that keep each Draco primitive's grid: for each axis, one point at the
        minimum (the origin), and one at the maximum of the widest axis (the range).  The other
        points at those extremes may move inwards; the grid's clip keeps them from passing."""
        pins = []
        for b in np.unique(bufs[(bufs >= _DRACO) & (bufs < UNSTORED)]).tolist():
            sel = np.flatnonzero(bufs == b)
            grid = self._encodings[int(enc[sel[0]])]
            if not isinstance(grid, DracoGrid):
                continue
            stored = np.frombuffer(self._buffers[b][0], "<f4").reshape(-1, 3)[offs[sel] // 12]
            ends = [np.argmin(stored[:, c]) for c in range(3)] + [np.argmax(stored[:, grid.axis])]
            pins += [int(part.slot_to_vertex[sel[k]]) for k in ends]
        return np.unique(np.array(pins, dtype=np.int64))

    def quantize_part(self, part: int, index: np.ndarray, vertices: np.ndarray,
                      decimals: int | None = None) -> np.ndarray:
        """Positions of vertices ``index`` of part ``part`` as writing then reading gives them.

        Each vertex goes to its accessor's grid (float32 or a quantized integer type); a vertex
        that cannot be written (no storage, or slots of different encodings) keeps its position.
        """
        v = np.asarray(vertices, dtype=np.float64)
        codes = self._vertex_encoding[part][np.asarray(index, dtype=np.int64)]
        out = np.empty_like(v)
        for code in np.unique(codes).tolist():
            sel = codes == code
            old = self.parts[part].vertices[np.asarray(index)[sel]]
            if code < 0:
                out[sel] = old
                continue
            enc = self._encodings[code]
            out[sel] = enc.quantize(v[sel])
        pins = self._draco_pins[part]
        if pins.size:  # one vertex at each end of each Draco grid fixes its origin and range
            keep = np.isin(np.asarray(index, dtype=np.int64), pins)
            out[keep] = self.parts[part].vertices[np.asarray(index)[keep]]
        return out

    def _patch(self, vertices: list[np.ndarray], moved: list[np.ndarray], decimals: int | None) -> bytes:
        new_buffers: dict[int, bytearray] = {}
        for part, v, m, (buf_idx, offsets, encs, writable) in zip(
            self.parts, vertices, moved, self._slots, strict=True
        ):
            if m.size == 0:
                continue
            sel = moved_slots(part, m) & writable & (buf_idx < UNSTORED)
            if not sel.any():
                continue
            coords = np.asarray(v, dtype=np.float64)[part.slot_to_vertex[sel]]
            sel_buf, sel_off, sel_enc = buf_idx[sel], offsets[sel], encs[sel]
            for b, e in {(int(b), int(e)) for b, e in zip(sel_buf.tolist(), sel_enc.tolist(), strict=True)}:
                if b not in new_buffers:
                    new_buffers[b] = bytearray(self._buffers[b][0])
                here = (sel_buf == b) & (sel_enc == e)
                patch_xyz(new_buffers[b], sel_off[here], self._encodings[e].encode(coords[here]))
        if not new_buffers:
            return self.data

        edits: list[tuple[str, int, str, str]] = []  # (section, index, member, new JSON text)
        for acc_idx, (bufs, offs, e) in self._positions.items():
            if not any(int(b) in new_buffers for b in np.unique(bufs).tolist()):
                continue
            enc = self._encodings[e]
            old = _gather(self._buffers, {}, bufs, offs, enc)
            new = _gather(self._buffers, new_buffers, bufs, offs, enc)
            if np.array_equal(old.view(f"u{enc.dtype.itemsize}"), new.view(f"u{enc.dtype.itemsize}")):
                continue
            acc = self._gltf["accessors"][acc_idx]
            low = np.array([new[:, c].min() for c in range(3)], dtype=enc.dtype)
            high = np.array([new[:, c].max() for c in range(3)], dtype=enc.dtype)
            del old, new
            for key, ext in (("min", low), ("max", high)):
                if key in acc and not enc.same_json(acc[key], ext):
                    edits.append(("accessors", acc_idx, key, enc.json_numbers(ext)))
        if any(b >= VIRTUAL for b in new_buffers):
            return self._reencode(new_buffers, edits)
        for b, buf in new_buffers.items():
            _, _, uri_head = self._buffers[b]
            if uri_head is not None:
                payload = base64.b64encode(bytes(buf)).decode("ascii")
                edits.append(("buffers", b, "uri", json.dumps(uri_head + "," + payload)))

        text = self._text
        if edits:
            spans = _member_spans(text)
            located = []
            for section, index, key, new_text in edits:
                span = spans.get((section, index, key))
                if span is None:  # cannot happen: spans follow json.loads' last-member-wins rule
                    raise RuntimeError(f"{section}[{index}].{key} not found in the JSON text")
                located.append((span, new_text))
            for (s, e), new_text in sorted(located, reverse=True):
                text = text[:s] + new_text + text[e:]

        if self._json_chunk is None:  # .gltf: everything lives in the JSON text
            return text.encode("utf-8")
        # GLB: splice the new JSON chunk and the patched BIN chunk between unchanged byte ranges
        # (one copy of the file; the BIN chunk always comes after the JSON chunk)
        data = memoryview(self.data)
        js, jl = self._json_chunk
        pieces: list[bytes | bytearray | memoryview] = []
        at = 0
        if text is not self._text:
            body = text.encode("utf-8")
            body += b" " * (-len(body) % 4)
            total = struct.unpack_from("<I", self.data, 8)[0] + len(body) - jl
            pieces += [self.data[:8], struct.pack("<III", total, len(body), CHUNK_JSON), body]
            at = js + jl
        bin_buf = self._buffers.get(0)
        if 0 in new_buffers and bin_buf is not None and bin_buf[1] is not None:
            start = bin_buf[1]
            pieces += [data[at:start], new_buffers[0]]
            at = start + len(new_buffers[0])
        pieces.append(data[at:])
        return b"".join(pieces)


    def _reencode(self, patched: dict[int, bytearray], edits: list[tuple[str, int, str, str]]) -> bytes:
        """Write a file whose compressed streams changed: re-encode them, splice them into their
        buffers (later data keeps its alignment) and serialise the JSON again."""
        gltf = json.loads(json.dumps(self._gltf))
        splices: dict[int, list[tuple[int, int, bytes]]] = {}
        done: set[str] = set()
        for b in sorted(b for b in patched if b >= VIRTUAL):
            if b < _DRACO:
                view_index = b - VIRTUAL
                ext = self._meshopt[view_index]
                source = self._buffers[ext.buffer][0]
                stream = encode_meshopt(ext, bytes(patched[b]), source[ext.offset : ext.offset + ext.length])
                splices.setdefault(ext.buffer, []).append((ext.offset, ext.length, stream))
                gltf["bufferViews"][view_index]["extensions"][ext.extension]["byteLength"] = len(stream)
                done.add("meshopt")
            else:
                d = self._draco[b - _DRACO]
                assert isinstance(d.grid, DracoGrid)  # others are pinned by quantize_part
                ext = d.primitive["extensions"][DRACO_EXTENSION]
                positions = np.frombuffer(bytes(patched[b]), "<f4").reshape(-1, 3)
                stream, semantics, points, faces = encode_draco(d.mesh, ext["attributes"], positions, d.grid,
                                                                d.header)
                view = gltf["bufferViews"][d.view]
                splices.setdefault(d.buffer, []).append((d.start, view["byteLength"], stream))
                view["byteLength"] = len(stream)
                path = self._primitive_path(d.primitive)
                prim = gltf["meshes"][path[0]]["primitives"][path[1]]
                prim["extensions"][DRACO_EXTENSION]["attributes"] = semantics
                # edgebreaker merges points equal in every attribute: the accessors follow the stream
                for acc in prim["attributes"].values():
                    gltf["accessors"][acc]["count"] = points
                if "indices" in prim:
                    gltf["accessors"][prim["indices"]]["count"] = 3 * faces
                done.add("draco")
        for section, index, key, new_text in edits:
            gltf[section][index][key] = json.loads(new_text)
        buffers = {b: bytes(buf) for b, buf in patched.items() if b < VIRTUAL}
        for b, pieces in splices.items():
            old = buffers.get(b, self._buffers[b][0])
            buffers[b], moved = _spliced(old, pieces)
            for view in gltf.get("bufferViews", []):
                if view.get("buffer") == b:
                    view["byteOffset"] = moved(view.get("byteOffset", 0))
                for name in MESHOPT_EXTENSIONS:
                    ext = (view.get("extensions") or {}).get(name)
                    if isinstance(ext, dict) and ext.get("buffer") == b:
                        ext["byteOffset"] = moved(ext.get("byteOffset", 0))
            gltf["buffers"][b]["byteLength"] = len(buffers[b])
        for b, buf in buffers.items():
            uri_head = self._buffers[b][2]
            if uri_head is not None:
                gltf["buffers"][b]["uri"] = uri_head + "," + base64.b64encode(buf).decode("ascii")
        self.reencoded = tuple(sorted(done))
        text = json.dumps(gltf, separators=(",", ":"), ensure_ascii=False)
        if self._json_chunk is None:
            return text.encode("utf-8")
        return _glb(self.data, text.encode("utf-8"), buffers.get(0))

    def _primitive_path(self, primitive: dict[str, Any]) -> tuple[int, int]:
        for mi, mesh in enumerate(self._gltf["meshes"]):
            for pi, prim in enumerate(mesh["primitives"]):
                if prim is primitive:
                    return mi, pi
        raise RuntimeError("Draco primitive not found")  # cannot happen: it comes from this JSON


@dataclass(frozen=True)
class _DracoPrimitive:
    """A decoded Draco primitive and where its stream lives (for re-encoding)."""

    primitive: dict[str, Any]
    mesh: Any
    view: int
    buffer: int
    start: int
    grid: DracoGrid | None
    header: bytes


def _spliced(old: bytes, pieces: list[tuple[int, int, bytes]]) -> tuple[bytes, Any]:
    """``old`` with the byte ranges ``(start, length)`` replaced, each new piece padded so that
    the data after it moves by a multiple of 4; and the map from old offsets to new ones."""
    pieces = sorted(pieces)
    out, at, starts, shifts = [], 0, [], []
    shift = 0
    for start, length, new in pieces:
        pad = (length - len(new)) % 4
        out += [old[at:start], new, b"\0" * pad]
        at = start + length
        shift += len(new) + pad - length
        starts.append(start + length)
        shifts.append(shift)
    out.append(old[at:])
    ends = np.array(starts)
    cumulative = np.array(shifts)

    def moved(offset: int) -> int:
        k = int(np.searchsorted(ends, offset, side="right"))
        return offset + (int(cumulative[k - 1]) if k else 0)

    return b"".join(out), moved


def _glb(data: bytes, json_body: bytes, bin_body: bytes | None) -> bytes:
    """A GLB like ``data`` with a new JSON chunk and, when given, a new BIN chunk (other chunks
    and any bytes after the declared length are kept)."""
    length = struct.unpack_from("<I", data, 8)[0]
    json_body += b" " * (-len(json_body) % 4)
    chunks = [struct.pack("<II", len(json_body), CHUNK_JSON) + json_body]
    off, seen_bin = 12, False
    off += 8 + struct.unpack_from("<I", data, 12)[0]
    while off < length:
        clen, ctype = struct.unpack_from("<II", data, off)
        body = data[off + 8 : off + 8 + clen]
        if ctype == CHUNK_BIN and not seen_bin and bin_body is not None:
            body = bin_body + b"\0" * (-len(bin_body) % 4)
        seen_bin |= ctype == CHUNK_BIN
        chunks.append(struct.pack("<II", len(body), ctype) + body)
        off += 8 + clen
    out = b"".join(chunks)
    return b"glTF" + struct.pack("<II", 2, 12 + len(out)) + out + data[length:]


def _encoding_name(enc: Encoding) -> str:
    name = {"f": "float", "i": "int", "u": "uint"}[enc.dtype.kind] + str(8 * enc.dtype.itemsize)
    return f"{name} normalized" if enc.normalized else name


def _gather(
    buffers: dict[int, tuple[bytes, int | None, str | None]],
    patched: dict[int, bytearray],
    bufs: np.ndarray,
    offs: np.ndarray,
    enc: Encoding,
) -> np.ndarray:
    """Stored components (``(k, 3)`` of ``enc.dtype``) of elements at ``(bufs, offs)``; zeros
    where an element has no storage."""
    out = np.zeros((len(bufs), enc.element_size), dtype=np.uint8)
    cols = np.arange(enc.element_size, dtype=np.int64)
    for b in np.unique(bufs).tolist():
        if b >= UNSTORED:
            continue
        here = bufs == b
        raw = np.frombuffer(patched[b] if b in patched else buffers[b][0], dtype=np.uint8)
        out[here] = raw[offs[here][:, None] + cols]
    return out.view(enc.dtype).reshape(-1, 3)


def _member_spans(text: str) -> dict[tuple[str, int, str], tuple[int, int]]:
    """Character spans of ``accessors[i].min/max`` and ``buffers[i].uri`` values in valid JSON.

    Follows json.loads: for duplicated members, the last one wins.
    """
    wanted = {("accessors", "min"), ("accessors", "max"), ("buffers", "uri")}
    spans: dict[tuple[str, int, str], tuple[int, int]] = {}
    stack: list[list[Any]] = []  # ["o", key, expecting_key] or ["a", index]
    opened: list[tuple[tuple[str, int, str], int] | None] = []
    for m in _TOKEN_RE.finditer(text):
        tok = m.group()
        top = stack[-1] if stack else None
        if tok == ":":
            if top is not None:
                top[2] = False
            continue
        if tok == ",":
            if top is not None:
                if top[0] == "o":
                    top[2] = True
                else:
                    top[1] += 1
            continue
        if tok in ("}", "]"):
            rec = opened.pop()
            stack.pop()
            if rec is not None:
                spans[rec[0]] = (rec[1], m.end())
            continue
        if top is not None and top[0] == "o" and top[2]:  # a member name
            top[1] = json.loads(tok)
            if len(stack) == 1 and top[1] in ("accessors", "buffers"):
                spans = {k: v for k, v in spans.items() if k[0] != top[1]}
            continue
        target = None
        if len(stack) == 3 and stack[0][0] == "o" and stack[1][0] == "a" and stack[2][0] == "o":
            if (stack[0][1], stack[2][1]) in wanted:
                target = (stack[0][1], stack[1][1], stack[2][1])
        if tok not in ("{", "["):  # a scalar value
            if target is not None:
                spans[target] = m.span()
        else:
            stack.append(["o", None, True] if tok == "{" else ["a", 0])
            opened.append((target, m.start()) if target is not None else None)
    return spans


def _reject_constant(name: str) -> Any:
    raise MeshFormatError(f"invalid JSON number {name}")


def _parse_json(text: str, where: str) -> dict[str, Any]:
    """Parse glTF JSON after checking its nesting depth (no recursion on hostile input)."""
    skeleton = _STRING_RE.sub("", text).encode("utf-8", "replace")
    codes = np.frombuffer(skeleton, dtype=np.uint8)
    step = np.isin(codes, (ord("{"), ord("["))).astype(np.int32) - np.isin(codes, (ord("}"), ord("]")))
    if codes.size and int(np.cumsum(step).max()) > MAX_JSON_DEPTH:
        raise MeshFormatError(f"JSON nested deeper than {MAX_JSON_DEPTH} levels", where)
    try:
        gltf = json.loads(text, parse_constant=_reject_constant)
    except (ValueError, RecursionError) as exc:
        raise MeshFormatError(f"invalid JSON: {str(exc)[:200]}", where) from None
    if not isinstance(gltf, dict):
        raise MeshFormatError("glTF JSON must be an object", where)
    asset = gltf.get("asset")
    version = asset.get("version") if isinstance(asset, dict) else None
    if not isinstance(version, str) or not version.startswith("2."):
        raise MeshFormatError("not a glTF 2.0 asset (asset.version must be '2.x')", "asset")
    return gltf


def _as_list(obj: dict[str, Any], key: str, where: str) -> list[Any]:
    value = obj.get(key, [])
    if not isinstance(value, list):
        raise MeshFormatError(f"'{key}' must be an array", where)
    return value


def _as_int(obj: dict[str, Any], key: str, where: str, default: int | None = None, minimum: int = 0) -> int:
    value = obj.get(key, default)
    if value is None:
        raise MeshFormatError(f"'{key}' is required", where)
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise MeshFormatError(f"'{key}' must be an integer >= {minimum}", where)
    return value


def _item(items: list[Any], index: Any, what: str, where: str) -> dict[str, Any]:
    if not isinstance(index, int) or isinstance(index, bool) or not 0 <= index < len(items):
        raise MeshFormatError(f"{what} index out of range (there are {len(items)})", where)
    item = items[index]
    if not isinstance(item, dict):
        raise MeshFormatError("must be an object", f"{what}[{index}]")
    return item


def _joined(arrays: list[np.ndarray]) -> np.ndarray:
    """``np.concatenate(arrays)``, without a copy for a single array (the usual one-primitive mesh)."""
    return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)


def _triangles(seq: np.ndarray, mode: int) -> np.ndarray:
    """Triangles of a TRIANGLES (4), TRIANGLE_STRIP (5) or TRIANGLE_FAN (6) index sequence."""
    n = len(seq)
    if mode == 4:
        return seq[: n - n % 3].reshape(-1, 3)
    if n < 3:
        return np.zeros((0, 3), np.int64)
    if mode == 5:  # one strip (glTF forbids restart values in indices)
        return strip_triangles(np.array([n]), seq)[1].reshape(-1, 3)
    k = np.arange(n - 2)
    return np.stack([np.full(n - 2, seq[0]), seq[k + 1], seq[k + 2]], axis=1)


class _Reader:
    """One parse of one file (holds the JSON, buffers and running limit counters)."""

    def __init__(self, data: bytes, limits: Limits) -> None:
        self.data = data
        self.limits = limits
        self.glb_bin: tuple[int, int] | None = None  # (start, length) of the GLB BIN chunk data
        self.gltf: dict[str, Any] = {}
        self.buffer_data: dict[int, tuple[bytes, int | None, str | None]] = {}
        self.decoded_bytes = 0  # bytes decoded from compressed views so far
        self.meshopt: dict[int, Any] = {}  # view index -> its MeshoptView
        self.draco: list[_DracoPrimitive] = []
        self.encodings: list[Encoding] = []
        self.total_slots = 0
        self.draco_views: set[int] = set()  # bufferViews of Draco streams decoded so far
        self.draco_discount = 0  # work not counted for first decodes of Draco streams (DRACO_DENSITY)
        self.skipped = 0  # point and line primitives, triangles that repeat a corner
        self.unstored = 0  # running fake offsets of elements with no storage

    # ---------------------------------------------------------------- containers
    def read_glb(self) -> GltfDocument:
        data = self.data
        if len(data) < 20:
            raise MeshFormatError("truncated GLB header", "byte 0")
        _, version, length = struct.unpack_from("<4sII", data, 0)
        if version != 2:
            raise MeshFormatError(f"unsupported GLB version {version} (only 2)", "byte 4")
        if length > len(data) or length < 20:
            raise MeshFormatError(f"GLB length {length} does not fit the {len(data)}-byte file", "byte 8")
        chunks: list[tuple[int, int, int]] = []
        off = 12
        while off < length:
            if length - off < 8:
                raise MeshFormatError("truncated GLB chunk header", f"byte {off}")
            clen, ctype = struct.unpack_from("<II", data, off)
            if clen > length - off - 8:
                raise MeshFormatError(f"GLB chunk length {clen} runs past the end of the file", f"byte {off}")
            chunks.append((ctype, off + 8, clen))
            off += 8 + clen
        if chunks[0][0] != CHUNK_JSON:
            raise MeshFormatError("the first GLB chunk must be JSON", "byte 16")
        _, js, jl = chunks[0]
        self.limits.check("json_bytes", jl)
        bins = [(s, n) for t, s, n in chunks[1:] if t == CHUNK_BIN]
        self.glb_bin = bins[0] if bins else None
        try:
            text = data[js : js + jl].rstrip(b"\x00" + _WS).decode("utf-8")
        except UnicodeDecodeError:
            raise MeshFormatError("GLB JSON chunk is not UTF-8", f"byte {js}") from None
        self.gltf = _parse_json(text, "GLB JSON chunk")
        return self._document(text, (js, jl))

    def read_gltf(self) -> GltfDocument:
        # the JSON size is checked on the bytes, before parsing builds anything from them (60 MB
        # of "{}" took 32 s and 1.9 GB to parse); embedded data: URIs do not count, as below
        embedded = sum(m.end() - m.start() for m in _DATA_URI_RE.finditer(self.data))
        self.limits.check("json_bytes", len(self.data) - embedded)
        try:
            text = self.data.decode("utf-8")
        except UnicodeDecodeError:
            raise MeshFormatError("glTF JSON is not UTF-8") from None
        self.gltf = _parse_json(text, "glTF JSON")
        embedded = 0
        for key in ("buffers", "images"):
            items = self.gltf.get(key)
            for item in items if isinstance(items, list) else []:
                uri = item.get("uri") if isinstance(item, dict) else None
                if isinstance(uri, str) and uri[:5].lower() == "data:":
                    embedded += len(uri)
        self.limits.check("json_bytes", len(text) - embedded)
        return self._document(text, None)

    # ---------------------------------------------------------------- buffers
    def _check_buffers(self) -> list[Any]:
        buffers = _as_list(self.gltf, "buffers", "buffers")
        for i, buf in enumerate(buffers):
            where = f"buffers[{i}]"
            if not isinstance(buf, dict):
                raise MeshFormatError("must be an object", where)
            _as_int(buf, "byteLength", where, minimum=1)
            uri = buf.get("uri")
            if uri is None and _is_fallback(buf):
                continue  # a meshopt fallback buffer: its views are read from their compressed copy
            if uri is None:
                if self.glb_bin is None or i != 0:
                    raise MeshFormatError("buffer has no uri (only GLB buffer 0, the BIN chunk, may)", where)
            elif not isinstance(uri, str) or uri[:5].lower() != "data:":
                raise MeshFormatError(
                    "external buffer refused: only embedded data: URIs (or a GLB BIN chunk) are read", where
                )
        return buffers

    def _buffer(self, index: int) -> bytes:
        """Bytes of buffer ``index`` (validated by :meth:`_check_buffers`), decoded once."""
        if index in self.buffer_data:
            return self.buffer_data[index][0]
        buf = self.gltf["buffers"][index]
        where = f"buffers[{index}]"
        uri = buf.get("uri")
        if uri is None and _is_fallback(buf):
            raise MeshFormatError("data read from a meshopt fallback buffer (it has no bytes)", where)
        if uri is None:
            assert self.glb_bin is not None
            start, n = self.glb_bin
            raw, file_offset, head = self.data[start : start + n], start, None
        else:
            head, comma, payload = uri.partition(",")
            if not comma or not head.lower().endswith(";base64"):
                raise MeshFormatError("data: URI must be base64-encoded", where)
            self.limits.check("bytes", len(payload) // 4 * 3)
            try:
                raw = base64.b64decode(payload, validate=True)
            except (binascii.Error, ValueError):
                raise MeshFormatError("invalid base64 in data: URI", where) from None
            file_offset = None
        if buf["byteLength"] > len(raw):
            raise MeshFormatError(f"byteLength {buf['byteLength']} > the {len(raw)} bytes stored", where)
        self.buffer_data[index] = (raw, file_offset, head)
        return raw

    def _layout(
        self, acc_index: int, elem_size: int, role: str, sparse_ok: bool = False
    ) -> tuple[int, int, int, int]:
        """Validated (buffer, byte offset, stride, count) of an accessor, nothing allocated.

        A meshopt-compressed bufferView is decoded (limits checked first) into a virtual buffer.
        With ``sparse_ok``, a sparse accessor's base is returned (buffer ``UNSTORED`` when it has
        no bufferView, implicit zeros) and :meth:`_sparse` reads the substitutions.
        """
        where = f"accessors[{acc_index}]"
        acc = _item(_as_list(self.gltf, "accessors", "accessors"), acc_index, "accessors", where)
        if "sparse" in acc and not sparse_ok:
            raise MeshFormatError(f"sparse {role} accessor is not supported", where)
        count = _as_int(acc, "count", where, minimum=1)
        if "bufferView" not in acc:
            if "sparse" in acc and sparse_ok:
                return UNSTORED, 0, elem_size, count
            raise MeshFormatError(f"{role} accessor has no bufferView (compressed or empty data)", where)
        acc_offset = _as_int(acc, "byteOffset", where, default=0)
        b, start, stride = self._view_span(acc["bufferView"], acc_offset, elem_size, count, where)
        return b, start, stride, count

    def _view_span(
        self, view_index: Any, offset: int, elem_size: int, count: int, where: str, packed: bool = False
    ) -> tuple[int, int, int]:
        """(buffer, byte offset, stride) of ``count`` elements from ``offset`` in a bufferView."""
        views = _as_list(self.gltf, "bufferViews", "bufferViews")
        view = _item(views, view_index, "bufferViews", where)
        vwhere = f"bufferViews[{view_index}]"
        buf = _item(_as_list(self.gltf, "buffers", "buffers"), view.get("buffer"), "buffers", vwhere)
        buf_index: int = view["buffer"]  # a valid index now
        view_offset = _as_int(view, "byteOffset", vwhere, default=0)
        view_length = _as_int(view, "byteLength", vwhere, minimum=1)
        stride = elem_size
        if "byteStride" in view and not packed:
            stride = _as_int(view, "byteStride", vwhere, minimum=4)
            if stride > 252 or stride < elem_size:
                raise MeshFormatError(f"byteStride {stride} invalid for {elem_size}-byte elements", vwhere)
        if offset + (count - 1) * stride + elem_size > view_length:
            raise MeshFormatError(
                f"{count} elements of stride {stride} from offset {offset} overrun the "
                f"{view_length}-byte bufferView",
                where,
            )
        compressed = meshopt_view(view, vwhere)
        if compressed is not None:
            if compressed.count * compressed.stride < view_length:
                raise MeshFormatError("meshopt stream decodes to fewer bytes than the bufferView", vwhere)
            if compressed.mode == "ATTRIBUTES" and compressed.stride != stride:
                raise MeshFormatError("meshopt byteStride differs from the bufferView's", vwhere)
            self._decoded_view(view_index, compressed, vwhere)
            return VIRTUAL + view_index, offset, stride
        if view_offset + view_length > buf["byteLength"]:
            raise MeshFormatError("bufferView runs past the end of its buffer", vwhere)
        if view_offset + view_length > len(self._buffer(buf_index)):
            raise MeshFormatError("bufferView runs past the stored buffer data", vwhere)
        return buf_index, view_offset + offset, stride

    def _decoded_view(self, view_index: int, ext: Any, where: str) -> None:
        """Decode a meshopt-compressed view once, into virtual buffer ``VIRTUAL + view_index``."""
        if VIRTUAL + view_index in self.buffer_data:
            return
        _item(_as_list(self.gltf, "buffers", "buffers"), ext.buffer, "buffers", where)
        source = self._buffer(ext.buffer)
        if ext.offset + ext.length > len(source):
            raise MeshFormatError(f"{ext.extension} stream runs past its buffer", where)
        self.decoded_bytes += ext.count * ext.stride
        self.limits.check("bytes", self.decoded_bytes)
        raw = decode_meshopt(ext, source[ext.offset : ext.offset + ext.length], self.limits, where)
        self.buffer_data[VIRTUAL + view_index] = (raw, None, None)
        self.meshopt[view_index] = ext

    def _sparse(self, acc_index: int, count: int, elem_size: int) -> tuple[np.ndarray, int, int] | None:
        """A sparse accessor's substituted element indices and where their values are stored."""
        where = f"accessors[{acc_index}].sparse"
        sparse = self.gltf["accessors"][acc_index].get("sparse")
        if sparse is None:
            return None
        if not isinstance(sparse, dict):
            raise MeshFormatError("must be an object", where)
        n = _as_int(sparse, "count", where, minimum=1)
        if n > count:
            raise MeshFormatError(f"{n} sparse elements for an accessor of {count}", where)
        indices, values = sparse.get("indices"), sparse.get("values")
        if not isinstance(indices, dict) or not isinstance(values, dict):
            raise MeshFormatError("sparse 'indices' and 'values' must be objects", where)
        ctype = indices.get("componentType")
        dtype = _INDEX_DTYPES.get(ctype) if type(ctype) is int else None
        if dtype is None:
            raise MeshFormatError("sparse indices must be UNSIGNED_BYTE/SHORT/INT", where)
        ib, istart, _ = self._view_span(indices.get("bufferView"), _as_int(indices, "byteOffset", where, 0),
                                        dtype.itemsize, n, where, packed=True)
        vb, vstart, _ = self._view_span(values.get("bufferView"), _as_int(values, "byteOffset", where, 0),
                                        elem_size, n, where, packed=True)
        idx = np.frombuffer(self._buffer(ib), dtype=dtype, count=n, offset=istart).astype(np.int64)
        if np.any(np.diff(idx) <= 0) or int(idx[-1]) >= count:
            raise MeshFormatError("sparse indices must increase strictly and stay below the count", where)
        return idx, vb, vstart

    def _buffer_any(self, index: int) -> bytes:
        """A buffer of the file or a decoded virtual one."""
        return self.buffer_data[index][0] if index >= VIRTUAL else self._buffer(index)

    def _position_slots(self, pos_index: int, awhere: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Positions of a POSITION accessor (float64, mesh-local) and where each element is stored.

        Returns
        -------
        positions : (k, 3) float64
        buffers, offsets : (k,) int64
            Buffer id and byte offset of each element's components.
        encoding : int
            Index into :attr:`encodings`.
        """
        acc = self.gltf["accessors"][pos_index]
        ctype = acc.get("componentType")
        dtype = POSITION_DTYPES.get(ctype) if type(ctype) is int else None
        normalized = acc.get("normalized", False)
        if dtype is None or acc.get("type") != "VEC3" or not isinstance(normalized, bool) or (
            normalized and ctype == FLOAT
        ):
            raise MeshFormatError(
                "POSITION accessor must be VEC3 of FLOAT or (KHR_mesh_quantization) BYTE, UNSIGNED_BYTE, "
                "SHORT or UNSIGNED_SHORT, normalized or not (FLOAT never normalized)",
                awhere,
            )
        enc = Encoding(dtype, normalized)
        b, start, stride, count = self._layout(pos_index, enc.element_size, "POSITION", sparse_ok=True)
        self.limits.check("vertices", self.total_slots + count)
        bufs = np.full(count, b, dtype=np.int64)
        if b == UNSTORED:
            raw = np.zeros((count, 3), dtype=dtype)
            offs = self.unstored + enc.element_size * np.arange(count, dtype=np.int64)
            self.unstored += enc.element_size * count
        else:
            raw = np.ndarray((count, 3), dtype=dtype, buffer=self._buffer_any(b), offset=start,
                             strides=(stride, dtype.itemsize))
            offs = start + stride * np.arange(count, dtype=np.int64)
        sparse = self._sparse(pos_index, count, enc.element_size)
        if sparse is not None:
            idx, vb, vstart = sparse
            raw = np.array(raw)
            values = np.frombuffer(self._buffer_any(vb), dtype=dtype, count=3 * len(idx), offset=vstart)
            raw[idx] = values.reshape(-1, 3)
            bufs[idx] = vb
            offs[idx] = vstart + enc.element_size * np.arange(len(idx), dtype=np.int64)
        positions = finite_float64(raw, awhere) if enc.is_float else enc.decode(raw)
        return positions, bufs, offs, self._encoding_id(enc)

    def _encoding_id(self, enc: Encoding) -> int:
        if enc not in self.encodings:
            self.encodings.append(enc)
        return self.encodings.index(enc)

    def _check_work(self, total_faces: int, n_prims: int) -> None:
        """:func:`_check_work` of the slots, faces and primitives read so far (first decodes of
        Draco streams at :data:`DRACO_DENSITY`)."""
        _check_work(self.total_slots + total_faces + PRIMITIVE_WORK * n_prims - self.draco_discount,
                    len(self.data))

    def _draco(self, prim: dict[str, Any], ext: Any, pwhere: str) -> tuple[np.ndarray, np.ndarray, int, int]:
        """Positions, triangles and POSITION accessor of a KHR_draco_mesh_compression primitive."""
        where = f"{pwhere}.extensions.{DRACO_EXTENSION}"
        attributes = prim.get("attributes", {})
        ids = ext.get("attributes") if isinstance(ext, dict) else None
        if not isinstance(ids, dict) or type(ids.get("POSITION")) is not int or ids["POSITION"] < 0:
            raise MeshFormatError("Draco extension needs attributes.POSITION", where)
        accessors = _as_list(self.gltf, "accessors", "accessors")
        pos_index = attributes["POSITION"]
        acc = _item(accessors, pos_index, "accessors", pwhere)
        count = _as_int(acc, "count", f"accessors[{pos_index}]", minimum=1)
        self.limits.check("vertices", self.total_slots + count)
        n_indices = None
        if "indices" in prim:
            iacc = _item(accessors, prim["indices"], "accessors", pwhere)
            n_indices = _as_int(iacc, "count", f"accessors[{prim['indices']}]", minimum=1)
        view_index = ext.get("bufferView")
        b, start, _ = self._view_span(view_index, 0, 1, 1, where, packed=True)
        if b >= VIRTUAL:
            raise MeshFormatError("a Draco stream in a meshopt-compressed bufferView", where)
        view = self.gltf["bufferViews"][view_index]
        data = self._buffer_any(b)[start : start + view["byteLength"]]
        mesh = decode_draco(bytes(data), ids["POSITION"], self.limits, where, count, n_indices)
        vid = _DRACO + len(self.draco)
        positions = finite_float64(mesh.positions, where)
        grid = draco_grid(mesh.positions)
        self.draco.append(_DracoPrimitive(prim, mesh, view_index, b, start, grid, bytes(data[:12])))
        self.buffer_data[vid] = (mesh.positions.astype("<f4").tobytes(), None, None)
        enc = self._encoding_id(grid if grid is not None else Encoding(np.dtype("<f4")))
        return positions, mesh.faces, vid, enc

    # ---------------------------------------------------------------- meshes
    def _document(self, text: str, json_chunk: tuple[int, int] | None) -> GltfDocument:
        gltf, limits = self.gltf, self.limits
        self._check_buffers()
        accessors = _as_list(gltf, "accessors", "accessors")
        meshes = _as_list(gltf, "meshes", "meshes")
        limits.check("meshes", len(meshes))
        total_faces = n_prims = 0
        parts: list[MeshPart] = []
        part_slots: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        positions: dict[int, tuple[np.ndarray, np.ndarray, int]] = {}
        index_ranges: list[tuple[int, int, int]] = []
        for mi, mesh in enumerate(meshes):
            mwhere = f"meshes[{mi}]"
            if not isinstance(mesh, dict):
                raise MeshFormatError("must be an object", mwhere)
            pos_list, tri_list, buf_list, off_list, enc_list = [], [], [], [], []
            n_slots = 0
            block_of: dict[int, tuple[int, int]] = {}  # POSITION accessor -> (first slot, count) here
            for pi, prim in enumerate(_as_list(mesh, "primitives", mwhere)):
                pwhere = f"{mwhere}.primitives[{pi}]"
                if not isinstance(prim, dict):
                    raise MeshFormatError("must be an object", pwhere)
                mode = _as_int(prim, "mode", pwhere, default=4)
                attributes = prim.get("attributes", {})
                if not isinstance(attributes, dict):
                    raise MeshFormatError("'attributes' must be an object", pwhere)
                if mode in _SKIPPED_MODES or "POSITION" not in attributes:
                    self.skipped += 1
                    continue
                if mode not in _TRIANGLE_MODES:
                    raise MeshFormatError(f"unknown primitive mode {mode}", pwhere)
                n_prims += 1
                pos_index = attributes["POSITION"]
                _item(accessors, pos_index, "accessors", pwhere)
                awhere = f"accessors[{pos_index}]"
                prim_exts = prim.get("extensions")
                draco = prim_exts.get(DRACO_EXTENSION) if isinstance(prim_exts, dict) else None
                if draco is not None:
                    pos, tri, vid, enc_id = self._draco(prim, draco, pwhere)
                    count = len(pos)
                    self.total_slots += count
                    total_faces += len(tri)
                    limits.check("faces", total_faces)
                    if self.draco[-1].view not in self.draco_views:
                        self.draco_views.add(self.draco[-1].view)
                        work = count + len(tri)
                        self.draco_discount += work - work // DRACO_DENSITY
                    self._check_work(total_faces, n_prims)
                    pos_list.append(pos)
                    tri_list.append(tri + n_slots if n_slots else tri)
                    buf_list.append(np.full(count, vid, dtype=np.int64))
                    off_list.append(12 * np.arange(count, dtype=np.int64))
                    enc_list.append(np.full(count, enc_id, np.int64))
                    positions[pos_index] = (buf_list[-1], off_list[-1], enc_id)
                    n_slots += count
                    continue
                shared = pos_index in block_of  # primitives of one mesh sharing positions: slots once
                if shared:
                    count = block_of[pos_index][1]
                else:
                    pos, bufs, offs, enc_id = self._position_slots(pos_index, awhere)
                    count = len(pos)
                    self.total_slots += count
                if "indices" in prim:
                    idx_index = prim["indices"]
                    iacc = _item(accessors, idx_index, "accessors", pwhere)
                    iwhere = f"accessors[{idx_index}]"
                    ctype = iacc.get("componentType")
                    dtype = _INDEX_DTYPES.get(ctype) if type(ctype) is int else None
                    if dtype is None or iacc.get("type") != "SCALAR":
                        raise MeshFormatError("indices must be UNSIGNED_BYTE/SHORT/INT SCALAR", iwhere)
                    ib, istart, istride, icount = self._layout(idx_index, dtype.itemsize, "indices")
                    n_faces = icount // 3 if mode == 4 else max(icount - 2, 0)
                    total_faces += n_faces
                    limits.check("faces", total_faces)
                    self._check_work(total_faces, n_prims)
                    # a view of the stored indices: weld() converts the triangles to int64 once
                    seq = np.ndarray(
                        (icount,), dtype=dtype, buffer=self._buffer(ib), offset=istart, strides=(istride,)
                    )
                    if seq.size and int(seq.max()) >= count:
                        raise MeshFormatError(f"index {int(seq.max())} >= POSITION count {count}", iwhere)
                    index_ranges.append((ib, istart, istart + (icount - 1) * istride + dtype.itemsize))
                else:
                    total_faces += count // 3 if mode == 4 else max(count - 2, 0)
                    limits.check("faces", total_faces)
                    self._check_work(total_faces, n_prims)
                    seq = np.arange(count, dtype=np.int64)
                tri = _triangles(seq, mode)
                first = block_of.setdefault(pos_index, (n_slots, count))[0]
                tri_list.append(tri.astype(np.int64) + first if first else tri)
                if shared:
                    continue
                pos_list.append(pos)
                buf_list.append(bufs)
                off_list.append(offs)
                enc_list.append(np.full(count, enc_id, dtype=np.int64))
                positions[pos_index] = (bufs, offs, enc_id)
                n_slots += count
            if not pos_list:
                continue
            name = mesh.get("name")
            triangles = _joined(tri_list)
            stored = _joined(pos_list)
            if len(self.draco) > 1:
                stored = _draco_seams(stored, _joined(buf_list), _joined(enc_list), self.encodings)
            vertices, faces, slot_to_vertex = weld(stored, triangles)
            self.skipped += len(triangles) - len(faces)
            parts.append(
                MeshPart(
                    name=name if isinstance(name, str) and name else f"mesh{mi}",
                    vertices=vertices,
                    faces=faces,
                    slot_to_vertex=slot_to_vertex,
                )
            )
            part_slots.append((_joined(buf_list), _joined(off_list), _joined(enc_list)))
        if not parts:
            raise DegenerateMeshError("no triangle mesh in the glTF file")
        sizes = np.array([e.element_size for e in self.encodings], dtype=np.int64)
        slots = _ownership(part_slots, index_ranges, sizes)
        return GltfDocument(
            self.data,
            parts,
            gltf=gltf,
            text=text,
            json_chunk=json_chunk,
            buffers=self.buffer_data,
            slots=slots,
            positions=positions,
            encodings=self.encodings,
            meshopt=self.meshopt,
            draco=self.draco,
            skipped=self.skipped,
        )


def _check_work(work: int, file_bytes: int) -> None:
    """Refuse files whose meshes reuse stored data for much more work than the file holds.

    The work grows with the slots, faces and primitives of all meshes; a small file whose meshes all point at
    one accessor (a 93 KB GLB of 256 meshes: 10 s of work) would make it grow without the bytes.
    Stored once, a slot takes 12 bytes and a face at least 3, so the work stays linear in size.
    """
    allowed = MAX_REUSE * (file_bytes // 12) + REUSE_ALLOWANCE
    if work > allowed:
        raise LimitExceededError("slots and faces (shared data)", work, allowed)


def _ownership(
    part_slots: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    index_ranges: list[tuple[int, int, int]],
    sizes: np.ndarray,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Add to each part's slots (buffer, offset, encoding) a mask of those it writes: the first
    use of each stored element.

    Refuses position elements that partly overlap each other (or one element read with two
    encodings) or index data, so that patching positions can never change another position or
    a face.  ``sizes``: bytes of an element of each encoding.
    """
    buf = _joined([b for b, _, _ in part_slots])
    off = _joined([o for _, o, _ in part_slots])
    enc = _joined([e for _, _, e in part_slots])
    keys = (buf << _KEY_SHIFT) | off
    if keys.size < 2 or np.all(keys[1:] > keys[:-1]):  # the usual layout: already sorted, no repeats
        unique, first = keys, np.arange(keys.size)
    else:
        unique, first = np.unique(keys, return_index=True)
    ends = unique + sizes[enc[first]]
    if np.any(unique[1:] < ends[:-1]) or np.any(enc != enc[first][np.searchsorted(unique, keys)]):
        raise MeshFormatError("POSITION accessors overlap each other partially")
    for b, start, end in index_ranges:
        lo = np.searchsorted(unique, (b << _KEY_SHIFT) + start - 12, side="left")
        hi = np.searchsorted(unique, (b << _KEY_SHIFT) + end, side="left")
        if np.any(ends[lo:hi] > (b << _KEY_SHIFT) + start):
            raise MeshFormatError("POSITION data overlaps index data")
    writable = np.zeros(keys.size, dtype=bool)
    writable[first] = True
    out = []
    at = 0
    for part_buf, part_off, part_enc in part_slots:
        out.append((part_buf, part_off, part_enc, writable[at : at + part_buf.size]))
        at += part_buf.size
    return out


def _draco_seams(positions: np.ndarray, bufs: np.ndarray, encs: np.ndarray,
                 encodings: list[Encoding]) -> np.ndarray:
    """Positions with the seams between a mesh's Draco primitives closed.

    Each primitive is quantized on its own grid, so a vertex that two primitives share (a
    material border) is stored at two positions up to a grid step apart, and the bit-exact weld
    would cut the mesh there.  A point of one primitive within ``sqrt(3)`` grid steps of points of
    other primitives takes the position of the first of them (never two points of one primitive
    together).  A moved seam vertex is written on each primitive's grid, which keeps its copies
    that close, and ``quantize_part`` gives the first copy's grid, which is what reading gives.
    """
    draco = (bufs >= _DRACO) & (bufs < UNSTORED)
    idx = np.flatnonzero(draco)
    if np.unique(bufs[idx]).size < 2:
        return positions
    grids = [encodings[k] for k in np.unique(encs[idx]).tolist()]
    steps = [e.delta for e in grids if isinstance(e, DracoGrid)]
    if not steps:
        return positions
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pts = positions[idx]
    pairs = cKDTree(pts).query_pairs(r=float(np.sqrt(3.0) * max(steps)), output_type="ndarray")
    prim = bufs[idx]
    pairs = pairs[prim[pairs[:, 0]] != prim[pairs[:, 1]]]
    if pairs.size == 0:
        return positions
    n = len(idx)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    order = np.lexsort((np.arange(n), label))
    first = np.empty(label.max() + 1, np.int64)
    first[label[order[::-1]]] = order[::-1]  # the smallest index of each component
    # within a component, each primitive's points must be one position (a UV seam repeats it)
    by = np.lexsort((prim, label))
    same_group = (label[by][1:] == label[by][:-1]) & (prim[by][1:] == prim[by][:-1])
    differ = np.any(pts[by][1:] != pts[by][:-1], axis=1) & same_group
    ok = np.bincount(label, minlength=label.max() + 1) > 1
    ok[label[by][1:][differ]] = False
    snap = ok[label]
    out = positions.copy()
    out[idx[snap]] = pts[first[label[snap]]]
    return out


def _is_fallback(buf: dict[str, Any]) -> bool:
    """A buffer that only stands for the uncompressed size of meshopt-compressed views."""
    exts = buf.get("extensions")
    if not isinstance(exts, dict):
        return False
    return any(isinstance(exts.get(n), dict) and exts[n].get("fallback") is True for n in MESHOPT_EXTENSIONS)


SPECS = (
    FormatSpec("glb", "GLB", "glTF/GLB", ("glb",), "model/gltf-binary", sniff, read),
    FormatSpec("gltf", "glTF", "glTF/GLB", ("gltf",), "model/gltf+json", sniff, read),
)
