"""Hostile file shapes of every format, grown to any size: the inputs of the linear-cost test
(``test_linear_cost.py``) and benchmark (``python -m bench cost``).

Each shape is a function ``size -> (filename, bytes)`` whose output is about ``size`` bytes and
aims at one place where a reader's cost could grow faster than the file: long or unterminated
strings, escapes, many properties or elements, deep nesting, shared buffers, many meshes, many
faces, long polygons.  Whether the reader refuses the file or reads it does not matter here: only
how long the answer takes per byte.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable

import numpy as np

from core.formats import tds
from tests.core.formats.helpers import chunk, to_glb

Shape = Callable[[int], tuple[str, bytes]]
_GLTF_HEAD = b'{"asset":{"version":"2.0"},"extras":'


def gltf_unclosed_escapes(size: int) -> tuple[str, bytes]:
    r"""An unterminated string of ``\"`` (finding 1: quadratic string pre-pass)."""
    return "a.gltf", _GLTF_HEAD + b'"' + b'\\"' * (size // 2)


def gltf_long_string(size: int) -> tuple[str, bytes]:
    return "a.gltf", _GLTF_HEAD + b'"' + b"a\\n" * (size // 3) + b'"}'


def gltf_empty_objects(size: int) -> tuple[str, bytes]:
    """``[{},{},...]`` (finding 6: the JSON size was checked after parsing it)."""
    return "a.gltf", _GLTF_HEAD + b"[" + b"{}," * (size // 3) + b"{}]}"


def gltf_deep_nesting(size: int) -> tuple[str, bytes]:
    return "a.gltf", _GLTF_HEAD + b"[" * size


def gltf_many_quotes(size: int) -> tuple[str, bytes]:
    """Many tiny strings: every quote opens or closes one."""
    return "a.gltf", _GLTF_HEAD + b"[" + b'"",' * (size // 3) + b'""]}'


def _octahedron_blob(n: int) -> tuple[bytes, int]:
    pos = np.random.default_rng(0).random((max(n, 3), 3), dtype=np.float64).astype("<f4")
    return pos.tobytes(), len(pos)


def glb_shared_meshes(size: int) -> tuple[str, bytes]:
    """256 meshes reusing one POSITION accessor (finding 8: 256 x the work of the bytes)."""
    blob, n = _octahedron_blob(size // 12)
    meta = {
        "asset": {"version": "2.0"},
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]} for _ in range(256)],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": n - n % 3, "type": "VEC3"}],
        "bufferViews": [{"buffer": 0, "byteLength": len(blob)}],
        "buffers": [{"byteLength": len(blob)}],
    }
    return "a.glb", to_glb(meta, blob)


def glb_shared_primitives(size: int) -> tuple[str, bytes]:
    """One mesh of as many primitives as the JSON holds, all on one small POSITION accessor."""
    blob, n = _octahedron_blob(300)
    k = max(size // 40, 1)
    meta = {
        "asset": {"version": "2.0"},
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}] * k}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": n, "type": "VEC3"}],
        "bufferViews": [{"buffer": 0, "byteLength": len(blob)}],
        "buffers": [{"byteLength": len(blob)}],
    }
    return "a.glb", to_glb(meta, blob)


def glb_many_accessors(size: int) -> tuple[str, bytes]:
    """Many meshes, each its own accessor over the same 36 bytes (aliased elements)."""
    blob, _ = _octahedron_blob(3)
    k = max(size // 150, 1)
    meta = {
        "asset": {"version": "2.0"},
        "meshes": [{"primitives": [{"attributes": {"POSITION": i}}]} for i in range(k)],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}] * k,
        "bufferViews": [{"buffer": 0, "byteLength": len(blob)}],
        "buffers": [{"byteLength": len(blob)}],
    }
    return "a.glb", to_glb(meta, blob)


def ply_many_properties(size: int) -> tuple[str, bytes]:
    """A header of distinct properties (finding 5: duplicate check by linear search)."""
    k = size // 24
    props = b"".join(b"property float p%d\n" % i for i in range(k))
    head = b"ply\nformat ascii 1.0\nelement vertex 0\n" + props + b"element face 0\n"
    return "a.ply", head + b"property list uchar int vertex_indices\nend_header\n"


def ply_many_elements(size: int) -> tuple[str, bytes]:
    k = size // 20
    els = b"".join(b"element e%d 0\n" % i for i in range(k))
    return "a.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\n" + els + (
        b"end_header\n"
    )


def ply_many_comments(size: int) -> tuple[str, bytes]:
    return "a.ply", b"ply\nformat ascii 1.0\n" + b"comment end_headerx\n" * (size // 20) + b"end_header\n"


def obj_many_faces(size: int) -> tuple[str, bytes]:
    """Face lines on three vertices (finding 8: faces were counted after tokenising)."""
    return "a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * (size // 8)


def obj_long_polygon(size: int) -> tuple[str, bytes]:
    return "a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf" + b" 1 2 3" * (size // 6) + b"\n"


def obj_many_statements(size: int) -> tuple[str, bytes]:
    """Lines of statements that are kept as text (groups, materials)."""
    return "a.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n" + b"g a\nusemtl m\n" * (size // 18)


def off_many_faces(size: int) -> tuple[str, bytes]:
    k = size // 8
    return "a.off", b"OFF\n3 %d 0\n0 0 0\n1 0 0\n0 1 0\n" % k + b"3 0 1 2\n" * k


def stl_ascii_many_facets(size: int) -> tuple[str, bytes]:
    facet = (b"facet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n"
             b"endloop\nendfacet\n")
    return "a.stl", b"solid a\n" + facet * (size // len(facet)) + b"endsolid a\n"


def stl_binary_many_facets(size: int) -> tuple[str, bytes]:
    k = max((size - 84) // 50, 1)
    rec = np.zeros(k, dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = np.random.default_rng(0).random((k, 3, 3))
    return "a.stl", b"\0" * 80 + struct.pack("<I", k) + rec.tobytes()


def tds_many_objects(size: int) -> tuple[str, bytes]:
    """Many one-triangle objects (each a few chunks)."""
    verts = chunk(tds.VERTICES, struct.pack("<H", 3) + np.eye(3, dtype="<f4").tobytes())
    faces = chunk(tds.FACES, struct.pack("<H", 1) + struct.pack("<4H", 0, 1, 2, 0))
    obj = chunk(tds.OBJECT, b"o\0" + chunk(tds.TRIMESH, verts + faces))
    k = max(size // len(obj), 1)
    return "a.3ds", chunk(tds.MAIN, chunk(tds.EDITOR, obj * k))


#: every shape by name, by format
SHAPES: dict[str, Shape] = {
    "gltf unclosed escapes": gltf_unclosed_escapes,
    "gltf long string": gltf_long_string,
    "gltf empty objects": gltf_empty_objects,
    "gltf deep nesting": gltf_deep_nesting,
    "gltf many quotes": gltf_many_quotes,
    "glb shared meshes": glb_shared_meshes,
    "glb shared primitives": glb_shared_primitives,
    "glb many accessors": glb_many_accessors,
    "ply many properties": ply_many_properties,
    "ply many elements": ply_many_elements,
    "ply many comments": ply_many_comments,
    "obj many faces": obj_many_faces,
    "obj long polygon": obj_long_polygon,
    "obj many statements": obj_many_statements,
    "off many faces": off_many_faces,
    "stl ascii many facets": stl_ascii_many_facets,
    "stl binary many facets": stl_binary_many_facets,
    "3ds many objects": tds_many_objects,
}


def describe() -> str:
    """The shapes as JSON (name -> docstring), for the benchmark's report."""
    return json.dumps({name: (fn.__doc__ or "").strip() for name, fn in SHAPES.items()}, indent=1)
