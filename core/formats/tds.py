"""3D Studio ``.3ds`` meshes (little-endian chunk tree).

A chunk is ``uint16 id`` + ``uint32 length`` (6-byte header included).  The path read is
main ``0x4D4D`` -> editor ``0x3D3D`` -> object ``0x4000`` (null-terminated name) -> triangle mesh
``0x4100`` -> vertex list ``0x4110`` (``uint16 count`` + ``count`` x 3 float32) and face list
``0x4120`` (``uint16 count`` + ``count`` x (3 uint16 corners + uint16 flags), then sub-chunks:
material groups ``0x4130``, smoothing groups ``0x4150``...).  Texture coordinates ``0x4140``, the
local matrix ``0x4160`` (vertices are stored already transformed, so it is not applied),
materials, lights, cameras and the keyframer ``0xB000`` are kept untouched.

Every chunk length on that path is checked against its parent and every count against the bytes
left in its chunk.  One :class:`MeshPart` per object with a triangle mesh (name = object name),
positions welded bit-exactly within the object.  Writing patches the moved vertices' float32
coordinates in place; every other byte is kept.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator

import numpy as np

from core.errors import DegenerateMeshError, MeshFormatError
from core.formats._binary import finite_float64, float32_xyz, moved_slots, patch_xyz
from core.formats.base import FormatSpec, Limits, MeshDocument, MeshPart, weld

MAIN = 0x4D4D
VERSION = 0x0002
EDITOR = 0x3D3D
OBJECT = 0x4000
TRIMESH = 0x4100
VERTICES = 0x4110
FACES = 0x4120
TEXCOORDS = 0x4140
MATRIX = 0x4160
KEYFRAMER = 0xB000


def sniff(data: bytes, name: str) -> bool:
    """A main chunk (``0x4D4D``) whose length fits the file, or a truncated one (to report it)."""
    if len(data) < 6:
        return False
    cid, length = struct.unpack_from("<HI", data, 0)
    if cid != MAIN or length < 6:
        return False
    if length <= len(data):
        return True
    return len(data) >= 8 and struct.unpack_from("<H", data, 6)[0] in (VERSION, EDITOR, KEYFRAMER)


def read(data: bytes, limits: Limits, name: str = "3ds") -> MeshDocument:
    """Parse a 3DS file.

    Parameters
    ----------
    data : bytes
        The whole file.
    limits : Limits
        Vertex, face and mesh counts are checked before reading each list.
    name : str
        Format key (``"3ds"``).

    Returns
    -------
    TdsDocument

    Raises
    ------
    MeshFormatError
        Truncated file, chunk running past its parent, count beyond its chunk, bad face index.
    LimitExceededError
        Too many vertices, faces or meshes.
    DegenerateMeshError
        No object with a triangle mesh.
    """
    if len(data) < 6:
        raise MeshFormatError("truncated 3DS header", "byte 0")
    cid, length = struct.unpack_from("<HI", data, 0)
    if cid != MAIN:
        raise MeshFormatError(f"not a 3DS file (first chunk 0x{cid:04X}, expected 0x4D4D)", "byte 0")
    if length < 6 or length > len(data):
        raise MeshFormatError(f"truncated 3DS: chunk says {length} bytes, file has {len(data)}", "byte 2")
    reader = _Reader(data, limits)
    for cid, start, end in _chunks(data, 6, length):
        if cid == EDITOR:
            for cid2, start2, end2 in _chunks(data, start, end):
                if cid2 == OBJECT:
                    reader.object(start2, end2)
    if not reader.parts:
        raise DegenerateMeshError("no triangle mesh in the 3DS file")
    return TdsDocument(data, reader.parts, reader.offsets)


class TdsDocument(MeshDocument):
    """A parsed 3DS file; :meth:`write` patches float32 vertex coordinates in place."""

    format = "3ds"
    encoding = "binary"
    storage_dtype = np.dtype(np.float32)

    def __init__(self, data: bytes, parts: list[MeshPart], offsets: list[np.ndarray]) -> None:
        super().__init__(data, parts)
        self._offsets = offsets  # per part, byte offset of every stored vertex

    def _patch(self, vertices: list[np.ndarray], moved: list[np.ndarray], decimals: int | None) -> bytes:
        out = bytearray(self.data)
        for part, v, m, offsets in zip(self.parts, vertices, moved, self._offsets, strict=True):
            if m.size == 0:
                continue
            sel = moved_slots(part, m)
            values = float32_xyz(np.asarray(v, dtype=np.float64)[part.slot_to_vertex[sel]])
            patch_xyz(out, offsets[sel], values)
        return bytes(out)


def _chunks(data: bytes, start: int, end: int) -> Iterator[tuple[int, int, int]]:
    """Yield ``(id, data start, end)`` of the chunks filling ``data[start:end]``, checking lengths."""
    off = start
    while off < end:
        if end - off < 6:
            raise MeshFormatError(f"truncated chunk header ({end - off} bytes left in parent)", f"byte {off}")
        cid, length = struct.unpack_from("<HI", data, off)
        if length < 6 or length > end - off:
            raise MeshFormatError(
                f"chunk 0x{cid:04X} length {length} runs past its parent (ending at byte {end})",
                f"byte {off}",
            )
        yield cid, off + 6, off + length
        off += length


def _count(data: bytes, start: int, end: int, item: int, what: str) -> int:
    """``uint16`` count at ``start`` of a list of ``item``-byte records that must fit before ``end``."""
    if end - start < 2:
        raise MeshFormatError(f"{what} chunk too short for its count", f"byte {start}")
    (n,) = struct.unpack_from("<H", data, start)
    if 2 + n * item > end - start:
        raise MeshFormatError(
            f"{what} count {n} runs past its chunk ({end - start - 2} bytes left)", f"byte {start}"
        )
    return int(n)


class _Reader:
    """Collects parts while walking objects (running totals for the limits)."""

    def __init__(self, data: bytes, limits: Limits) -> None:
        self.data = data
        self.limits = limits
        self.parts: list[MeshPart] = []
        self.offsets: list[np.ndarray] = []
        self.total_vertices = 0
        self.total_faces = 0

    def object(self, start: int, end: int) -> None:
        nul = self.data.find(b"\0", start, end)
        if nul < 0:
            raise MeshFormatError("object name is not null-terminated inside its chunk", f"byte {start}")
        name = self.data[start:nul].decode("latin-1")
        for cid, s, e in _chunks(self.data, nul + 1, end):
            if cid == TRIMESH:
                self.trimesh(name, s, e)

    def trimesh(self, name: str, start: int, end: int) -> None:
        data = self.data
        vertex_list: tuple[int, int] | None = None
        face_list: tuple[int, int] | None = None
        for cid, s, e in _chunks(data, start, end):
            if cid == VERTICES:
                if vertex_list is not None:
                    raise MeshFormatError("several vertex lists in one mesh", f"byte {s - 6}")
                vertex_list = (s + 2, _count(data, s, e, 12, "vertex"))
            elif cid == FACES:
                if face_list is not None:
                    raise MeshFormatError("several face lists in one mesh", f"byte {s - 6}")
                n = _count(data, s, e, 8, "face")
                face_list = (s + 2, n)
                for _ in _chunks(data, s + 2 + 8 * n, e):  # material / smoothing groups: lengths only
                    pass
            elif cid == TEXCOORDS:
                _count(data, s, e, 8, "texture coordinate")
            elif cid == MATRIX and e - s < 48:
                raise MeshFormatError("local matrix chunk shorter than 48 bytes", f"byte {s - 6}")
        if face_list is None or face_list[1] == 0:
            return  # no triangles: nothing the engine can use
        if vertex_list is None:
            raise MeshFormatError("object has faces but no vertex list", f"byte {start - 6}")
        vstart, nv = vertex_list
        fstart, nf = face_list
        self.limits.check("meshes", len(self.parts) + 1)
        self.total_vertices += nv
        self.limits.check("vertices", self.total_vertices)
        self.total_faces += nf
        self.limits.check("faces", self.total_faces)
        positions = np.frombuffer(data, dtype="<f4", count=3 * nv, offset=vstart).reshape(-1, 3)
        faces = np.frombuffer(data, dtype="<u2", count=4 * nf, offset=fstart).reshape(-1, 4)[:, :3]
        faces = faces.astype(np.int64)
        if int(faces.max()) >= nv:
            raise MeshFormatError(
                f"face corner {int(faces.max())} >= vertex count {nv} of its object", f"byte {fstart}"
            )
        positions = finite_float64(positions, f"vertex list of the object at byte {start - 6}")
        vertices, welded, slot_to_vertex = weld(positions, faces)
        self.parts.append(MeshPart(name=name, vertices=vertices, faces=welded, slot_to_vertex=slot_to_vertex))
        self.offsets.append(vstart + 12 * np.arange(nv, dtype=np.int64))


SPEC = FormatSpec("3ds", "3DS", "3DS", ("3ds",), "application/x-3ds", sniff, read)
