"""Named tiny meshes and a writer for every format, shared by the format tests and the service's
hostile-upload tests (meshio's ``tests/helpers.py``).

The meshes are small enough to check by hand: coordinates are exact in float32 and have at most two
decimals, so every format stores them exactly.  The writers take ``(vertices, faces)`` and return
file bytes; none reads anything from disk.
"""

from __future__ import annotations

import base64
import json
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.formats import gltf, tds

# ------------------------------------------------------------------------------- named meshes


@dataclass(frozen=True)
class TinyMesh:
    """A named mesh: ``vertices`` (n, 3) float64, ``faces`` (m, 3) int64 (outward orientation)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray

    def triangles(self) -> set[frozenset[tuple[float, float, float]]]:
        """The faces as sets of corner positions: independent of vertex numbering and corner order."""
        return {frozenset(map(tuple, self.vertices[f].tolist())) for f in self.faces}


TETRAHEDRON = TinyMesh(
    "tetrahedron",
    np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64),
    np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int64),
)
#: two triangles: an open mesh, every vertex on the boundary
SQUARE = TinyMesh(
    "square",
    np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64),
    np.array([[0, 1, 2], [0, 2, 3]], np.int64),
)
OCTAHEDRON = TinyMesh(
    "octahedron",
    np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64) * 0.5,
    np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]],
             np.int64),
)
TINY = (TETRAHEDRON, SQUARE, OCTAHEDRON)

# ------------------------------------------------------------------------------------ text formats


def _rows(faces: np.ndarray | list[list[int]]) -> list[list[int]]:
    """Faces as lists of corners (polygons of any size)."""
    return faces.tolist() if isinstance(faces, np.ndarray) else [list(f) for f in faces]


def obj_text(vertices: np.ndarray, faces: np.ndarray | list[list[int]], head: str = "") -> bytes:
    lines = [head] if head else []
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, np.float64).tolist()]
    lines += ["f " + " ".join(str(i + 1) for i in f) for f in _rows(faces)]
    return ("\n".join(lines) + "\n").encode()


def off_text(vertices: np.ndarray, faces: np.ndarray | list[list[int]]) -> bytes:
    lines = ["OFF", f"{len(vertices)} {len(faces)} 0"]
    lines += [" ".join(repr(c) for c in v) for v in np.asarray(vertices, np.float64).tolist()]
    lines += [" ".join(map(str, [len(f), *f])) for f in _rows(faces)]
    return ("\n".join(lines) + "\n").encode()


def ply_header(fmt: str, vertices: int, faces: int, count: str = "uchar", index: str = "int") -> bytes:
    return (f"ply\nformat {fmt} 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {faces}\nproperty list {count} {index} vertex_indices\n"
            "end_header\n").encode()


def ply_ascii(vertices: np.ndarray, faces: np.ndarray | list[list[int]]) -> bytes:
    lines = [" ".join(repr(float(c)) for c in v) for v in vertices]
    lines += [" ".join(map(str, [len(f), *f])) for f in _rows(faces)]
    return ply_header("ascii", len(vertices), len(faces)) + ("\n".join(lines) + "\n").encode()


def ply_binary(vertices: np.ndarray, faces: np.ndarray | list[list[int]], index: str = "i",
               endian: str = "<") -> bytes:
    """Binary PLY (``endian`` ``<`` or ``>``) with float coordinates and uchar-counted int (``i``)
    or uint (``I``) index lists."""
    fmt = "binary_little_endian" if endian == "<" else "binary_big_endian"
    out = [ply_header(fmt, len(vertices), len(faces), index="int" if index == "i" else "uint")]
    out.append(np.asarray(vertices, f"{endian}f4").tobytes())
    for face in _rows(faces):
        out.append(struct.pack(f"{endian}B{len(face)}{index}", len(face), *face))
    return b"".join(out)


def stl_ascii(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    lines = ["solid tiny"]
    for tri in np.asarray(vertices, np.float64)[np.asarray(faces)].tolist():
        lines += ["  facet normal 0 0 0", "    outer loop"]
        lines += [f"      vertex {x!r} {y!r} {z!r}" for x, y, z in tri]
        lines += ["    endloop", "  endfacet"]
    return ("\n".join([*lines, "endsolid tiny"]) + "\n").encode()


def binary_stl(triangles: np.ndarray, header: bytes = b"binary stl", attr: int = 0,
               count: int | None = None) -> bytes:
    """A binary STL of the ``(n, 3, 3)`` corners, zero normals; ``count`` overrides the declared
    facet count."""
    tris = np.asarray(triangles, "<f4").reshape(-1, 3, 3)
    records = np.zeros(len(tris), dtype=[("n", "<f4", 3), ("c", "<f4", (3, 3)), ("a", "<u2")])
    records["c"] = tris
    records["a"] = attr
    n = len(tris) if count is None else count
    return header.ljust(80, b" ")[:80] + struct.pack("<I", n) + records.tobytes()


# ------------------------------------------------------------------------------------------ glTF


def gltf_document(vertices: np.ndarray, faces: np.ndarray,
                  name: str = "ball") -> tuple[dict[str, Any], bytes]:
    """A one-mesh glTF (JSON dict, binary buffer) of float32 positions and uint32 indices."""
    pos = np.asarray(vertices, "<f4").tobytes()
    idx = np.asarray(faces, "<u4").tobytes()
    v = np.asarray(vertices, np.float32)
    meta: dict[str, Any] = {
        "asset": {"version": "2.0"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"name": name, "primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(v), "type": "VEC3",
             "min": v.min(axis=0).tolist(), "max": v.max(axis=0).tolist()},
            {"bufferView": 1, "componentType": 5125, "count": int(np.size(faces)), "type": "SCALAR"},
        ],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(pos)},
                        {"buffer": 0, "byteOffset": len(pos), "byteLength": len(idx)}],
        "buffers": [{"byteLength": len(pos) + len(idx)}],
    }
    return meta, pos + idx


def data_uri(blob: bytes) -> str:
    return "data:application/octet-stream;base64," + base64.b64encode(blob).decode()


def to_gltf(meta: dict[str, Any], blob: bytes | None = None, indent: int | None = 2) -> bytes:
    """``.gltf`` JSON text; ``blob`` (when given) becomes buffer 0 as a ``data:`` URI."""
    meta = json.loads(json.dumps(meta))
    if blob is not None:
        meta["buffers"][0]["uri"] = data_uri(blob)
    return json.dumps(meta, indent=indent).encode()


def to_glb(meta: dict[str, Any], blob: bytes | None) -> bytes:
    """GLB container for a JSON dict and an optional BIN chunk."""
    text = json.dumps(meta, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    out = struct.pack("<II", len(text), gltf.CHUNK_JSON) + text
    if blob is not None:
        blob += b"\0" * (-len(blob) % 4)
        out += struct.pack("<II", len(blob), gltf.CHUNK_BIN) + blob
    return b"glTF" + struct.pack("<II", 2, 12 + len(out)) + out


# ------------------------------------------------------------------------------------------- 3DS


def chunk(cid: int, body: bytes) -> bytes:
    return struct.pack("<HI", cid, 6 + len(body)) + body


def trimesh_chunk(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A 3DS triangle mesh with texture coordinates, a local matrix, material and smoothing groups."""
    n, m = len(vertices), len(faces)
    vl = chunk(tds.VERTICES, struct.pack("<H", n) + np.asarray(vertices, "<f4").tobytes())
    uv = chunk(tds.TEXCOORDS, struct.pack("<H", n) + np.zeros((n, 2), "<f4").tobytes())
    matrix = chunk(tds.MATRIX, np.eye(4, 3, dtype="<f4").tobytes())
    rec = np.zeros((m, 4), "<u2")
    rec[:, :3] = faces
    rec[:, 3] = 7
    groups = chunk(0x4130, b"steel\0" + struct.pack("<H", m) + np.arange(m, dtype="<u2").tobytes())
    smooth = chunk(0x4150, np.ones(m, "<u4").tobytes())
    fl = chunk(tds.FACES, struct.pack("<H", m) + rec.tobytes() + groups + smooth)
    return chunk(tds.TRIMESH, vl + uv + matrix + fl)


def make_3ds(objects: list[tuple[str, bytes]]) -> bytes:
    """A 3DS file with the given (name, object body chunks) objects."""
    editor = chunk(0x3D3E, struct.pack("<I", 3)) + b"".join(
        chunk(tds.OBJECT, name.encode() + b"\0" + body) for name, body in objects
    )
    return chunk(tds.MAIN, chunk(tds.VERSION, struct.pack("<I", 3)) + chunk(tds.EDITOR, editor)
                 + chunk(tds.KEYFRAMER, chunk(0xB00A, b"\0" * 8)))


# -------------------------------------------------------------------------- every format, by name

#: (format, encoding) -> writer of a tiny mesh in that format and encoding
WRITERS: dict[tuple[str, str], Callable[[TinyMesh], bytes]] = {
    ("obj", "ascii"): lambda m: obj_text(m.vertices, m.faces, head=f"o {m.name}"),
    ("off", "ascii"): lambda m: off_text(m.vertices, m.faces),
    ("ply", "ascii"): lambda m: ply_ascii(m.vertices, m.faces),
    ("ply", "binary_little_endian"): lambda m: ply_binary(m.vertices, m.faces),
    ("ply", "binary_big_endian"): lambda m: ply_binary(m.vertices, m.faces, endian=">"),
    ("stl", "ascii"): lambda m: stl_ascii(m.vertices, m.faces),
    ("stl", "binary"): lambda m: binary_stl(m.vertices[m.faces]),
    ("glb", "binary"): lambda m: to_glb(*gltf_document(m.vertices, m.faces, m.name)),
    ("gltf", "ascii"): lambda m: to_gltf(*gltf_document(m.vertices, m.faces, m.name)),
    ("3ds", "binary"): lambda m: make_3ds([(m.name, trimesh_chunk(m.vertices, m.faces))]),
}
