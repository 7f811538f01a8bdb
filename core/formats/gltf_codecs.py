"""Compressed glTF geometry: EXT/KHR_meshopt_compression buffer views and KHR_draco_mesh_compression.

Decoding uses the reference decoders (meshoptimizer's C library through the ``meshoptimizer``
package, Google's Draco through ``DracoPy``); neither is handed a stream before what it would
allocate is known and within :class:`~core.formats.base.Limits`:

- meshopt: the decoded size is ``count * byteStride`` (the extension says both), checked against
  ``max_bytes`` and the vertex/face limits, with the stream's version byte and the mode's stride
  rules, before the decoder runs; the decoder itself never reads past the bytes it is given.
- Draco: the header and connectivity header are parsed here (magic, version 2.2, mesh encoder,
  sequential or edgebreaker connectivity, face and vertex counts) and the counts checked against
  the limits and the glTF accessors' declared counts before ``DracoPy`` sees the stream.

Encoding (writing a marked file back) re-encodes with the settings read from the file: the
meshopt stream version, stride, mode and filter; Draco's position quantization grid (origin,
range and bits, recovered from the decoded positions) and the other attributes as decoded.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from core.errors import MeshFormatError
from core.formats.base import Limits
from core.formats.gltf_accessors import Encoding

MESHOPT_EXTENSIONS = ("EXT_meshopt_compression", "KHR_meshopt_compression")
DRACO_EXTENSION = "KHR_draco_mesh_compression"
_MODES = ("ATTRIBUTES", "TRIANGLES", "INDICES")
_FILTERS = ("NONE", "OCTAHEDRAL", "QUATERNION", "EXPONENTIAL", "COLOR")
#: first byte of each stream kind: vertex codec v0/v1, index codec v0/v1, index sequence v1
_STREAM_HEADERS = {"ATTRIBUTES": (0xA0, 0xA1), "TRIANGLES": (0xE0, 0xE1), "INDICES": (0xD1,)}


@dataclass(frozen=True)
class MeshoptView:
    """A buffer view compressed with EXT/KHR_meshopt_compression, as the extension declares it.

    Attributes
    ----------
    extension : str
        Which of :data:`MESHOPT_EXTENSIONS`.
    buffer, offset, length : int
        Where the compressed bytes are.
    stride, count : int
        Decoded element size and count (decoded size = ``stride * count``).
    mode, filter : str
    """

    extension: str
    buffer: int
    offset: int
    length: int
    stride: int
    count: int
    mode: str
    filter: str


def meshopt_view(view: dict[str, Any], where: str) -> MeshoptView | None:
    """The meshopt extension of a buffer view, validated (``None`` when it has none)."""
    exts = view.get("extensions")
    if not isinstance(exts, dict):
        return None
    for name in MESHOPT_EXTENSIONS:
        ext = exts.get(name)
        if ext is None:
            continue
        if not isinstance(ext, dict):
            raise MeshFormatError(f"{name} must be an object", where)
        values = {}
        for key, default, minimum in (("buffer", None, 0), ("byteOffset", 0, 0), ("byteLength", None, 1),
                                      ("byteStride", None, 1), ("count", None, 1)):
            value = ext.get(key, default)
            if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
                raise MeshFormatError(f"{name}.{key} must be an integer >= {minimum}", where)
            values[key] = value
        mode, filt = ext.get("mode"), ext.get("filter", "NONE")
        if mode not in _MODES:
            raise MeshFormatError(f"{name}.mode must be one of {', '.join(_MODES)}", where)
        if filt not in _FILTERS or (filt != "NONE" and mode != "ATTRIBUTES"):
            raise MeshFormatError(f"{name}.filter {filt!r} is invalid for mode {mode}", where)
        stride = values["byteStride"]
        if mode == "ATTRIBUTES" and (stride % 4 or stride > 256):
            raise MeshFormatError(f"{name}.byteStride must be a multiple of 4 up to 256", where)
        if mode != "ATTRIBUTES" and stride not in (2, 4):
            raise MeshFormatError(f"{name}.byteStride must be 2 or 4 for {mode}", where)
        if mode == "TRIANGLES" and values["count"] % 3:
            raise MeshFormatError(f"{name}.count must be a multiple of 3 for TRIANGLES", where)
        return MeshoptView(name, values["buffer"], values["byteOffset"], values["byteLength"], stride,
                           values["count"], mode, filt)
    return None


def decode_meshopt(ext: MeshoptView, source: bytes, limits: Limits, where: str) -> bytes:
    """Decoded bytes (``ext.count * ext.stride``) of a meshopt stream, limits checked first.

    Parameters
    ----------
    ext : MeshoptView
    source : bytes
        The compressed stream (``ext.length`` bytes).
    limits : Limits
    where : str
        Location for errors.

    Raises
    ------
    LimitExceededError
        Decoded size or element count over the limits.
    MeshFormatError
        An unknown stream version, a filter the decoder lacks, or a stream the decoder refuses.
    """
    limits.check("bytes", ext.count * ext.stride)
    if ext.mode == "ATTRIBUTES":
        limits.check("vertices", ext.count)
    else:
        limits.check("faces", ext.count // 3)
    if len(source) < 1 or source[0] not in _STREAM_HEADERS[ext.mode]:
        raise MeshFormatError(f"unknown {ext.extension} {ext.mode} stream header", where)
    import meshoptimizer  # imported on first use: most files have no compressed view

    try:
        if ext.mode == "ATTRIBUTES":
            out = meshoptimizer.decode_vertex_buffer(ext.count, ext.stride, source,
                                                     dtype=np.dtype(f"V{ext.stride}"))
            raw = out.view(np.uint8)
            if ext.filter == "EXPONENTIAL":
                raw = meshoptimizer.decode_filter_exp(raw, ext.count, ext.stride)
            elif ext.filter != "NONE":  # never on positions or indices: those are all we decode
                raise MeshFormatError(f"{ext.extension} filter {ext.filter} on a position view", where)
            return raw.tobytes()
        # the index codecs do not depend on the index size: decode as 32 bits (the package's
        # result array is uint32 whatever size it is asked for)
        if ext.mode == "TRIANGLES":
            indices = meshoptimizer.decode_index_buffer(ext.count, 4, source)
        else:
            indices = meshoptimizer.decode_index_sequence(ext.count, 4, source)
        if ext.stride == 2 and indices.size and int(indices.max()) > 0xFFFF:
            raise MeshFormatError(f"{ext.extension} index above 65535 in a 2-byte view", where)
    except (ValueError, RuntimeError) as exc:
        raise MeshFormatError(f"{ext.extension} stream does not decode ({exc})", where) from None
    return indices.astype("<u2" if ext.stride == 2 else "<u4").tobytes()


def encode_meshopt(ext: MeshoptView, decoded: bytes, original: bytes) -> bytes:
    """Re-encode a decoded view with the settings of its original stream (same version, mode)."""
    import meshoptimizer

    version = original[0] & 0x0F
    if ext.mode == "ATTRIBUTES":
        if ext.filter != "NONE":
            raise MeshFormatError(f"writing {ext.extension} positions with the {ext.filter} filter "
                                  "is not supported")
        meshoptimizer.encode_vertex_version(version)
        data = np.frombuffer(decoded, dtype=np.uint8).reshape(ext.count, ext.stride)
        return meshoptimizer.encode_vertex_buffer(data, ext.count, ext.stride)
    indices = np.frombuffer(decoded, dtype="<u2" if ext.stride == 2 else "<u4").astype(np.uint32)
    n = int(indices.max()) + 1 if indices.size else 0
    if ext.mode == "TRIANGLES":
        meshoptimizer.encode_index_version(version)
        return meshoptimizer.encode_index_buffer(indices, ext.count, n)
    return meshoptimizer.encode_index_sequence(indices, ext.count, n)


def _varint(data: bytes, at: int, where: str) -> tuple[int, int]:
    value = shift = 0
    while True:
        if at >= len(data) or shift > 28:
            raise MeshFormatError("truncated Draco header", where)
        byte = data[at]
        value |= (byte & 0x7F) << shift
        at += 1
        if not byte & 0x80:
            return value, at
        shift += 7


def draco_counts(data: bytes, where: str) -> tuple[int, int]:
    """``(faces, vertices)`` declared by a Draco mesh stream's header, without decoding it.

    ``vertices`` is the connectivity's vertex count (edgebreaker splits attribute seams into
    more points, at most 3 per face).

    Raises
    ------
    MeshFormatError
        Not a Draco 2.2 triangle-mesh stream, metadata present, or a truncated header.
    """
    if len(data) < 12 or data[:5] != b"DRACO":
        raise MeshFormatError("not a Draco stream (no DRACO header)", where)
    major, minor, encoder, method = data[5], data[6], data[7], data[8]
    flags = int.from_bytes(data[9:11], "little")
    if (major, minor) != (2, 2):
        raise MeshFormatError(f"Draco bitstream {major}.{minor} is not supported (only 2.2)", where)
    if encoder != 1 or method not in (0, 1):
        raise MeshFormatError("Draco stream is not a triangle mesh", where)
    if flags & 0x8000:
        raise MeshFormatError("Draco metadata is not supported", where)
    if method == 0:  # sequential: faces then points
        faces, at = _varint(data, 11, where)
        points, _ = _varint(data, at, where)
        return faces, points
    vertices, at = _varint(data, 12, where)  # edgebreaker: traversal type byte first
    faces, _ = _varint(data, at, where)
    return faces, vertices


@dataclass(frozen=True)
class DracoMesh:
    """A decoded Draco primitive.

    Attributes
    ----------
    positions : (n, 3) float32 ndarray
        The POSITION attribute, as the decoder dequantizes it.
    faces : (m, 3) int64 ndarray
    attributes : list of dict
        Every attribute as DracoPy gives it (``unique_id``, ``attribute_type``, ``data``...).
    """

    positions: np.ndarray
    faces: np.ndarray
    attributes: list[dict[str, Any]]


def decode_draco(data: bytes, position_id: int, limits: Limits, where: str,
                 declared_vertices: int, declared_indices: int | None) -> DracoMesh:
    """Decode a KHR_draco_mesh_compression stream after checking its declared counts.

    Raises
    ------
    LimitExceededError
        Faces or vertices over the limits.
    MeshFormatError
        Counts that contradict the glTF accessors, or a stream the decoder refuses.
    """
    faces, vertices = draco_counts(data, where)
    limits.check("faces", faces)
    limits.check("vertices", max(vertices, declared_vertices))
    if declared_indices is not None and declared_indices != 3 * faces:
        raise MeshFormatError(
            f"Draco stream has {faces} faces, the indices accessor {declared_indices} indices", where)
    if declared_vertices > 3 * faces or vertices > 3 * faces:
        raise MeshFormatError("Draco stream declares more vertices than its faces can use", where)
    limits.check("bytes", 12 * 3 * faces + 24 * declared_vertices)
    import DracoPy  # imported on first use

    try:
        mesh = DracoPy.decode(data)
    except Exception as exc:
        raise MeshFormatError(f"Draco stream does not decode ({str(exc)[:200]})", where) from None
    attributes = list(getattr(mesh, "attributes", []) or [])
    pos = next((a for a in attributes if a.get("unique_id") == position_id), None)
    if pos is None or np.asarray(pos["data"]).ndim != 2 or np.asarray(pos["data"]).shape[1] != 3:
        raise MeshFormatError(f"Draco stream has no 3-component attribute {position_id} for POSITION", where)
    positions = np.asarray(pos["data"], dtype=np.float32)
    tri = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    if len(positions) != declared_vertices:
        raise MeshFormatError(f"Draco stream decodes {len(positions)} positions, the accessor declares "
                              f"{declared_vertices}", where)
    if tri.size and (tri.min() < 0 or tri.max() >= len(positions)):
        raise MeshFormatError("Draco face index out of range", where)
    return DracoMesh(positions, tri, attributes)


@dataclass(frozen=True)
class DracoGrid(Encoding):
    """The quantization grid of a Draco primitive's positions: ``origin + q * delta`` per axis,
    ``0 <= q <= qmax``, in float32 arithmetic as Draco's decoder computes it.

    Draco writes the grid (origin, range, bits) into its stream; the decoder does not give them
    back, so :func:`draco_grid` recovers them from the decoded positions and checks that every
    position is reproduced exactly.
    """

    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    delta: float = 1.0
    bits: int = 1
    axis: int = 0  # the widest axis, whose extent sets the range

    @property
    def top(self) -> float:
        """The largest coordinate on :attr:`axis`: a vertex there fixes the range and stays put."""
        return float(np.float32(self.qmax) * np.float32(self.delta) + np.float32(self.origin[self.axis]))

    @property
    def qmax(self) -> int:
        return (1 << self.bits) - 1

    @property
    def range(self) -> float:
        """The quantization range that gives the same ``delta``."""
        return float(np.float32(self.delta) * np.float32(self.qmax))

    def encode(self, coords: np.ndarray) -> np.ndarray:
        o, d = np.asarray(self.origin, np.float32), np.float32(self.delta)
        q = np.clip(np.rint((np.asarray(coords, np.float64) - o) / float(d)), 0, self.qmax)
        return (q.astype(np.float32) * d + o).astype("<f4")


def draco_grid(positions: np.ndarray) -> DracoGrid | None:
    """The Draco quantization grid that reproduces ``positions`` (float32) exactly, or ``None``.

    The origin is the minimum per axis (the vertex quantized to 0); ``delta`` follows from the
    widest axis, whose maximum is quantized to ``2**bits - 1``; the bits are estimated from the
    smallest gap between coordinates and confirmed on every position.
    """
    p = np.asarray(positions, np.float32)
    if len(p) == 0:
        return None
    o = p.min(axis=0)
    ext = p.max(axis=0) - o
    w = int(np.argmax(ext))
    if ext[w] <= 0:
        return None
    col = np.unique(p[:, w])
    gap = float(np.diff(col).min()) if len(col) > 1 else float(ext[w])
    guess = int(np.clip(round(np.log2(float(ext[w]) / gap + 1)), 1, 30))
    # a step below a few float32 spacings of the largest coordinate is no grid an encoder reproduces
    floor = 4 * float(np.spacing(np.abs(p).max()))
    for bits in [guess, *range(guess + 1, 31), *range(guess - 1, 0, -1)]:
        qmax = (1 << bits) - 1
        delta = np.float32(np.float32(ext[w]) / np.float32(qmax))
        if delta <= floor:
            continue
        origin = (float(o[0]), float(o[1]), float(o[2]))
        grid = DracoGrid(np.dtype("<f4"), False, origin, float(delta), bits, w)
        if np.float32(np.float32(grid.range) / np.float32(qmax)) != delta:
            continue
        if np.array_equal(grid.encode(p), p):
            return grid
    return None


def encode_draco(mesh: DracoMesh, semantics: dict[str, int], positions: np.ndarray, grid: DracoGrid,
                 header: bytes) -> tuple[bytes, dict[str, int], int, int]:
    """Re-encode a Draco primitive with new positions and the settings of its stream.

    Positions go on the same grid (the origin is given to the encoder; the range is the same as
    long as the widest axis keeps its extremes, which :meth:`DracoGrid` users pin); the
    connectivity coder is the stream's (sequential, or edgebreaker with the valence traversal at
    compression level 10, else level 7).  Texture coordinates keep their grid's bits where it can
    be recovered (else 12), normals get 10 bits (glTF-Transform's and gltf-pipeline's default:
    octahedral bits are not recoverable), other attributes are stored as decoded.

    Parameters
    ----------
    semantics : dict
        The extension's ``attributes``: glTF semantic -> Draco unique id.

    Returns
    -------
    stream : bytes
    semantics : dict
        The same semantics with the unique ids of the new stream.
    points, faces : int
        What the new stream decodes to (the encoder merges points equal in every attribute).

    Raises
    ------
    MeshFormatError
        An attribute DracoPy cannot store, or a re-encoding that would not read back as
        ``positions``.
    """
    import DracoPy

    by_id = {int(a["unique_id"]): a for a in mesh.attributes}
    pos_id = semantics["POSITION"]
    kwargs: dict[str, Any] = {}
    generic: dict[int, np.ndarray] = {}
    kinds: dict[int, str] = {}  # old unique id -> how it was passed
    for uid, a in by_id.items():
        if uid == pos_id:
            continue
        data = np.asarray(a["data"])
        data = data.reshape(len(data), -1)
        kind = {1: "normals", 2: "colors", 3: "tex_coord"}.get(int(a.get("attribute_type", 4)), "")
        if kind == "normals" and data.shape[1] == 3 and "normals" not in kwargs:
            kwargs["normals"], kwargs["normal_quantization_bits"] = data.astype(np.float64), 10
        elif kind == "tex_coord" and data.shape[1] == 2 and "tex_coord" not in kwargs:
            uv = data.astype(np.float64)
            g = draco_grid(np.c_[uv, np.zeros(len(uv))].astype(np.float32))
            kwargs["tex_coord"], kwargs["tex_coord_quantization_bits"] = uv, g.bits if g else 12
        elif kind == "colors" and data.dtype == np.uint8 and "colors" not in kwargs:
            kwargs["colors"] = data
        elif data.dtype in (np.float32, np.uint8, np.uint16, np.uint32):
            generic[uid], kind = data, "generic"
        else:
            raise MeshFormatError(f"Draco attribute {uid} of type {data.dtype} cannot be re-encoded")
        kinds[uid] = kind
    sequential = header[8] == 0
    level = 10 if not sequential and len(header) > 11 and header[11] == 2 else 7
    try:
        stream = DracoPy.encode(
            np.asarray(positions, np.float32), mesh.faces.astype(np.uint32), quantization_bits=grid.bits,
            compression_level=level, quantization_origin=list(grid.origin), preserve_order=sequential,
            generic_attributes=generic or None, **kwargs,
        )
        again = DracoPy.decode(stream)
    except Exception as exc:
        raise MeshFormatError(f"Draco re-encoding failed ({str(exc)[:200]})") from None
    new = list(getattr(again, "attributes", []) or [])
    types = {"normals": 1, "colors": 2, "tex_coord": 3}
    new_ids: dict[int, int] = {}
    for uid, kind in kinds.items():
        if kind == "generic":
            new_ids[uid] = uid
        else:
            new_ids[uid] = next(int(a["unique_id"]) for a in new if int(a["attribute_type"]) == types[kind])
    new_pos = [a for a in new if int(a["unique_id"]) not in new_ids.values()]
    if len(new_pos) != 1:
        raise MeshFormatError("Draco re-encoding lost track of its attributes")
    new_ids[pos_id] = int(new_pos[0]["unique_id"])
    got = np.asarray(new_pos[0]["data"], np.float32)
    want = np.asarray(positions, np.float32)
    same = np.array_equal(np.unique(got.view("V12").ravel()), np.unique(want.view("V12").ravel()))
    if not same:
        raise MeshFormatError("Draco re-encoding would not give the marked positions back")
    ids = {name: new_ids.get(uid, uid) for name, uid in semantics.items()}
    return bytes(stream), ids, len(got), len(np.asarray(again.faces).reshape(-1, 3))
